"""Fit the virtual-marker table (gst.body.markers) on BlazePose detections in synthetic worlds.

    python -m gst.lift.marker_worlds --seed 5010 --out DATA  # once per tuning world (5000+)
    python -m gst.fuse.fit_markers DATA/detections_5*.npz  # writes gst/body/markers_blazepose.json

Every crop of a tuning world comes with the truth body that was rendered. For each landmark and
each candidate frame joint (its anchor, the anchor's kinematic parent, the neck for the face, the
ankle, foot and knee for heel and toes), the offset is the one that best explains the landmark in
every crop it was detected in: robust (Cauchy, `sigma_px`) Gauss-Newton on the reprojection
error in full-image pixels, 3 unknowns per marker over all crops. Left and right markers choose
their frame together (smallest summed robust cost) and are made mirror images (x negated) of
their average. The JSON records the worlds, the crop count and each marker's median reprojection
error (px), so a refit can be compared.

Fitting in 2D, not against triangulated landmarks, weighs each detection by what it says (one
pixel, in its own camera) and needs no second view: occluded or single-view crops count too.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from gst.atomic import atomic_write_text
from gst.body import load_body_model
from gst.body.markers import BLAZEPOSE_NAMES, DEFAULT_PARENTS, MarkerModel, default_markers_path
from gst.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS
from gst.fuse.marker_data import MarkerData, load_marker_data

__all__ = ["fit_marker_model", "fit_offsets", "MARKER_ANCHORS"]

_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
# The joint each landmark is anchored at (heels at the ankle, toes at the foot joint).
MARKER_ANCHORS: dict[str, str] = {n: DEFAULT_PARENTS[n][0] for n in BLAZEPOSE_NAMES}


def _candidates(name: str) -> list[int]:
    a = _J[MARKER_ANCHORS[name]]
    out = {a}
    if SMPL_PARENTS[a] >= 0:
        out.add(int(SMPL_PARENTS[a]))
    if MARKER_ANCHORS[name] == "head":
        out.add(_J["neck"])
    if "heel" in name or "foot_index" in name:
        side = name.split("_")[0]
        out |= {_J[f"{side}_knee"], _J[f"{side}_ankle"], _J[f"{side}_foot"]}
    return sorted(out)


def _mirror(name: str) -> str:
    for a, b in (("left", "right"), ("right", "left")):
        if a in name:
            return name.replace(a, b)
    return name


def fit_offsets(
    anchors: np.ndarray,
    frames: np.ndarray,
    uv: np.ndarray,
    conf: np.ndarray,
    cameras: tuple[np.ndarray, np.ndarray, np.ndarray],
    scale: np.ndarray,
    sigma_px: float = 4.0,
    iterations: int = 12,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust offsets of M markers given posed bodies.

    anchors (N, M, 3): anchor joint positions per crop; frames (N, M, 3, 3): frame joint world
    rotations; uv (N, M, 2) detections in crop pixels with conf (N, M); cameras = (K (N, 3, 3),
    R (N, 3, 3), t (N, 3)) of each crop; scale (N,) crop px -> full px.
    Returns offsets (M, 3), robust cost per marker (M,), median error in full px (M,)."""
    K, R, t = cameras
    M = anchors.shape[1]
    o = np.zeros((M, 3))

    def project(o: np.ndarray):
        X = anchors + np.einsum("nmij,mj->nmi", frames, o)
        cam = np.einsum("nij,nmj->nmi", R, X) + t[:, None]
        q = np.einsum("nij,nmj->nmi", K, cam)
        return q[..., :2] / q[..., 2:], cam[..., 2:]

    for _ in range(iterations):
        p, z = project(o)
        res = (p - uv) * scale[:, None, None]
        w = conf / (1 + (res**2).sum(-1) / sigma_px**2)
        P = (K[:, None, :2, :] - p[..., :, None] * np.array([0.0, 0.0, 1.0])) / z[..., None]
        D = P @ R[:, None] @ frames * scale[:, None, None, None]  # d res / d o, (N, M, 2, 3)
        H = np.einsum("nmki,nm,nmkj->mij", D, w, D) + 1e-9 * np.eye(3)
        g = np.einsum("nmki,nm,nmk->mi", D, w, res)
        o = o - np.linalg.solve(H, g[..., None])[..., 0]
    p, _ = project(o)
    err = np.linalg.norm(p - uv, axis=-1) * scale[:, None]
    cost = (conf * np.log1p(err**2 / sigma_px**2)).sum(0) / np.maximum(conf.sum(0), 1e-9)
    med = np.array([np.median(err[conf[:, m] > 0.5, m]) for m in range(M)])
    return o, cost, med


def fit_marker_model(data: MarkerData, body_spec: str = "anny", sigma_px: float = 4.0):
    body = load_body_model(body_spec, dtype=torch.float64)
    with torch.no_grad():
        out = body(
            torch.as_tensor(data.betas, dtype=torch.float64),
            torch.as_tensor(data.body_pose, dtype=torch.float64),
            torch.as_tensor(data.global_orient, dtype=torch.float64),
            torch.as_tensor(data.transl, dtype=torch.float64),
            vertex_ids=torch.zeros(1, dtype=torch.long),
            return_transforms=True,
        )
    joints = out.joints.numpy()
    rots = out.joint_transforms[..., :3, :3].numpy()
    uv = data.landmarks[..., :2].astype(np.float64)
    conf = data.landmarks[..., 2].astype(np.float64)
    conf = np.where(conf >= 0.1, conf, 0.0)
    cams = (data.K, data.R, data.t)
    names = BLAZEPOSE_NAMES
    anchor = np.array([_J[MARKER_ANCHORS[n]] for n in names])
    table: dict[int, dict[int, tuple[np.ndarray, float, float]]] = {}
    for m, name in enumerate(names):
        table[m] = {}
        for f in _candidates(name):
            o, c, med = fit_offsets(
                joints[:, anchor[m : m + 1]], rots[:, [f]], uv[:, m : m + 1], conf[:, m : m + 1],
                cams, data.px_scale, sigma_px,
            )  # fmt: skip
            table[m][f] = (o[0], float(c[0]), float(med[0]))
    frames = np.zeros(len(names), np.int64)
    offsets = np.zeros((len(names), 3))
    median_px = [0.0] * len(names)
    flip = np.array([-1.0, 1.0, 1.0])
    for m, name in enumerate(names):
        r = names.index(_mirror(name))
        if r < m:
            continue  # done with its pair
        pairs = [
            (table[m][f][1] + table[r][fr][1], f, fr)
            for f in table[m]
            if (fr := _J[_mirror(SMPL_JOINT_NAMES[f])]) in table[r]
        ]
        _, fm, fr = min(pairs)
        om, orr = table[m][fm][0], table[r][fr][0]
        if r != m:
            avg = (om + orr * flip) / 2
            om, orr = avg, avg * flip
        frames[m], frames[r] = fm, fr
        offsets[m], offsets[r] = om, orr
        median_px[m], median_px[r] = round(table[m][fm][2], 2), round(table[r][fr][2], 2)
    info = {
        "fitted": True,
        "body_model": body_spec,
        "worlds": sorted(int(w) for w in np.unique(data.world)),
        "crops": int(len(data.frame)),
        "median_reprojection_px": dict(zip(names, median_px, strict=True)),
        "method": "robust reprojection fit of each offset over all crops of the truth bodies; "
        "left/right mirrored (gst.fuse.fit_markers)",
    }
    return MarkerModel(names, anchor, offsets, info, frames)


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
    atomic_write_text(args.out, json.dumps(model.to_json(), indent=1) + "\n")
    res = model.info["median_reprojection_px"]
    print(f"{args.out}: {model.info['crops']} crops; median reprojection per marker (px): {res}")


if __name__ == "__main__":
    main()
