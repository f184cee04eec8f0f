"""Fit the virtual-marker table (gst.body.markers) on BlazePose detections in synthetic worlds.

    python -m gst.fuse.marker_data --seed 5000 --out DATA      # once per tuning world (5000+)
    python -m gst.fuse.fit_markers DATA/detections_5*.npz      # writes gst/body/markers_blazepose.json

For every (world, frame, person) the detected landmarks of all cameras are triangulated
(gst.fuse.triangulate, robust), and the truth body of that person is posed. Each landmark is
anchored at its default joint (gst.body.markers.DEFAULT_PARENTS); for each candidate frame (the
anchor, its kinematic parent, and for the face the neck) the offset is the robust mean of
R_f^T (X - J_a) over all samples (samples beyond 2.5 x the median residual are dropped, twice).
Left and right markers choose their frame together (smallest summed median residual) and are
made mirror images (x negated) of their average. The JSON records the worlds, the sample count and each marker's median
residual (mm) so a refit can be compared.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from gst.body import load_body_model
from gst.body.markers import (
    BLAZEPOSE_NAMES,
    DEFAULT_PARENTS,
    MarkerModel,
    default_markers_path,
)
from gst.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS
from gst.fuse.marker_data import MarkerData, load_marker_data
from gst.fuse.triangulate import triangulate_points

__all__ = ["triangulate_marker_data", "fit_marker_model"]

_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}


def triangulate_marker_data(data: MarkerData, min_views: int = 3):
    """Per (world, frame, person): triangulated landmarks (S, 33, 3) and the data row of one of
    its crops (for the truth body), keeping samples seen by at least `min_views` cameras."""
    key = np.stack([data.world, data.frame, data.person], 1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    C = int(data.camera.max()) + 1
    S, M = len(uniq), data.landmarks.shape[1]
    K = np.broadcast_to(np.eye(3), (S, C, 3, 3)).copy()
    Rt = np.broadcast_to(np.eye(3, 4), (S, C, 3, 4)).copy()
    uv = np.full((S, C, M, 2), np.nan)
    conf = np.zeros((S, C, M))
    scale = np.ones((S, C))
    K[inv, data.camera] = data.K
    Rt[inv, data.camera] = np.concatenate([data.R, data.t[..., None]], -1)
    uv[inv, data.camera] = data.landmarks[..., :2]
    conf[inv, data.camera] = data.landmarks[..., 2]
    scale[inv, data.camera] = data.px_scale
    n_views = np.zeros(S, int)
    np.add.at(n_views, inv, 1)
    first = np.full(S, -1)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    tri = triangulate_points(
        np.repeat(K[:, None], M, 1).reshape(S * M, C, 3, 3),
        np.repeat(Rt[:, None], M, 1).reshape(S * M, C, 3, 4),
        np.moveaxis(uv, 2, 1).reshape(S * M, C, 2),
        np.moveaxis(conf, 2, 1).reshape(S * M, C),
        np.repeat(scale[:, None], M, 1).reshape(S * M, C),
    )
    keep = n_views >= min_views
    return tri.points.reshape(S, M, 3)[keep], first[keep]


def _candidates(name: str) -> list[int]:
    """Frames tried for a landmark: its anchor, the anchor's parent, and the neck for the face."""
    anchor = _J[DEFAULT_PARENTS[name][0]]
    out = [anchor]
    if SMPL_PARENTS[anchor] >= 0:
        out.append(SMPL_PARENTS[anchor])
    if DEFAULT_PARENTS[name][0] == "head":
        out.append(_J["neck"])
    return out


def _mirror_name(name: str) -> str | None:
    for a, b in (("left", "right"), ("right", "left")):
        if a in name:
            return name.replace(a, b)
    return None


def _robust_offset(local: np.ndarray) -> tuple[np.ndarray, float, int]:
    keep = np.ones(len(local), bool)
    for _ in range(3):
        o = local[keep].mean(0)
        d = np.linalg.norm(local - o, axis=1)
        keep = d <= 2.5 * np.median(d)
    return o, float(np.median(d)), int(keep.sum())


def fit_marker_model(data: MarkerData, body_spec: str = "anny") -> MarkerModel:
    points, rows = triangulate_marker_data(data)
    body = load_body_model(body_spec, dtype=torch.float64)
    with torch.no_grad():
        out = body(
            torch.as_tensor(data.betas[rows], dtype=torch.float64),
            torch.as_tensor(data.body_pose[rows], dtype=torch.float64),
            torch.as_tensor(data.global_orient[rows], dtype=torch.float64),
            torch.as_tensor(data.transl[rows], dtype=torch.float64),
            vertex_ids=torch.zeros(1, dtype=torch.long),
            return_transforms=True,
        )
    joints = out.joints.numpy()
    rots = out.joint_transforms[..., :3, :3].numpy()
    anchor = np.array([_J[DEFAULT_PARENTS[n][0]] for n in BLAZEPOSE_NAMES])
    # per landmark and candidate frame: (offset, median residual, samples kept)
    table: dict[int, dict[int, tuple[np.ndarray, float, int]]] = {}
    for m, name in enumerate(BLAZEPOSE_NAMES):
        X = points[:, m]
        ok = np.isfinite(X).all(1)
        table[m] = {
            f: _robust_offset(np.einsum("sji,sj->si", rots[ok, f], X[ok] - joints[ok, anchor[m]]))
            for f in _candidates(name)
        }
    frames = np.zeros(len(BLAZEPOSE_NAMES), np.int64)
    offsets = np.zeros((len(BLAZEPOSE_NAMES), 3))
    residual_mm, counts = [0.0] * len(frames), [0] * len(frames)
    mirror = np.array([-1.0, 1.0, 1.0])
    for m, name in enumerate(BLAZEPOSE_NAMES):
        other = _mirror_name(name)
        r = BLAZEPOSE_NAMES.index(other) if other in BLAZEPOSE_NAMES else m
        if r < m:
            continue  # done with its pair
        pairs = []  # (summed residual, frame of m, frame of r)
        for f in table[m]:
            fr = _J[_mirror_name(SMPL_JOINT_NAMES[f]) or SMPL_JOINT_NAMES[f]]
            if fr in table[r]:
                pairs.append((table[m][f][1] + table[r][fr][1], f, fr))
        _, fm, fr = min(pairs)
        frames[m], frames[r] = fm, fr
        om, orr = table[m][fm][0], table[r][fr][0]
        if r != m:
            avg = (om + orr * mirror) / 2
            om, orr = avg, avg * mirror
        offsets[m], offsets[r] = om, orr
        for k, f in ((m, fm), (r, fr)):
            residual_mm[k] = round(table[k][f][1] * 1000, 1)
            counts[k] = table[k][f][2]
    info = {
        "fitted": True,
        "body_model": body_spec,
        "worlds": sorted(int(w) for w in np.unique(data.world)),
        "samples": int(len(rows)),
        "samples_used": dict(zip(BLAZEPOSE_NAMES, counts, strict=True)),
        "median_residual_mm": dict(zip(BLAZEPOSE_NAMES, residual_mm, strict=True)),
        "method": "robust mean offset of triangulated BlazePose landmarks in the parent "
        "joint's frame of the truth body; left/right mirrored (gst.fuse.fit_markers)",
    }
    return MarkerModel(BLAZEPOSE_NAMES, anchor, offsets, info, frames)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("detections", nargs="+", type=Path, help="detections_<seed>.npz files")
    ap.add_argument("--out", type=Path, default=default_markers_path())
    ap.add_argument("--body", default="anny")
    args = ap.parse_args(argv)
    data = load_marker_data(args.detections)
    if (data.world < 5000).any():
        raise SystemExit("marker fitting uses tuning worlds (seeds 5000+) only")
    model = fit_marker_model(data, args.body)
    args.out.write_text(json.dumps(model.to_json(), indent=1) + "\n")
    res = model.info["median_residual_mm"]
    print(f"{args.out}: {model.info['samples']} samples; median residual per marker (mm): {res}")


if __name__ == "__main__":
    main()
