"""Exact truth of a synthetic scene (docs/formats/synth_scene.md), mapped onto extracted crops.

The scene's truth is read by `synth.truth` (the format's owner): one row per (frame, person)
with body-model parameters, world joints and the motion label. `attach_scene_truth` matches
each extracted crop to the person it shows (`match_truth_views`) and gives the crop set the
truth keys every consumer needs: world and camera joints, 2D joints in crop pixels, visibility,
rotations (global orientation in the crop's camera) and betas, for evaluation and for the 2D/3D
fine-tuning baselines. Truth meshes are posed on demand (`SceneTruth.vertices`): the scene writes
parameters, and `body(betas, body_pose, global_orient, transl)` reproduces its world vertices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from scipy.optimize import linear_sum_assignment

from calibration.formats import read_rig
from gst.data.external import IdMaskFile
from gst.detect.boxes import box_iou
from gst.train.views import CropSet
from synth.truth import SceneTruth, read_scene_truth, read_truth_views, truth_mask_file

__all__ = [
    "attach_scene_truth",
    "mask_hits",
    "mask_truth_ids",
    "match_truth_views",
    "select_rows",
    "shown_ids",
]


def attach_scene_truth(
    crops: CropSet, boxes: np.ndarray, scene_dir: str | Path, min_iou: float = 0.3
) -> SceneTruth:
    """Match every crop to the truth person it shows and add truth keys to `crops.truth`:
    has_truth (N,) bool, truth_row (N,) index into the returned SceneTruth (-1: unmatched),
    joints_world / joints_cam (N,24,3), joints2d (N,24,2) crop px, visible (N,24),
    rotmats_cam (N,24,3,3) (index 0: global orientation in the crop's camera), betas (N,nb).
    Unmatched crops carry zeros (identity rotations, the rest pose); always filter with
    has_truth."""
    scene_dir = Path(scene_dir)
    truth = read_scene_truth(scene_dir)
    views = read_truth_views(scene_dir)
    view_rows = match_truth_views(crops, boxes, scene_dir, min_iou)
    index = truth.row_index()
    v_frame, v_pid, v_visible = views.frame, views.person_id, views.visible
    n = len(crops)
    row = np.full(n, -1, np.int64)
    visible = np.zeros((n, 24), np.float32)
    for i, r in enumerate(view_rows):
        if r >= 0:
            row[i] = index[(int(v_frame[r]), int(v_pid[r]))]
            visible[i] = v_visible[r]
    has = row >= 0
    safe = np.where(has, row, 0)
    jw = torch.from_numpy(truth.joints_world[safe]) * torch.from_numpy(has)[:, None, None]
    jc = jw @ crops.R.transpose(1, 2) + crops.t[:, None]
    z = jc[..., 2:].clamp_min(1e-6)
    uv = (jc / z) @ crops.K.transpose(1, 2)
    rot = axis_angle_to_rotation_matrix(
        torch.from_numpy(
            np.concatenate([truth.global_orient[safe][:, None], truth.body_pose[safe]], 1)
        ).reshape(-1, 3)
    ).reshape(n, 24, 3, 3)
    rot[:, 0] = crops.R @ rot[:, 0]  # body -> world, then world -> this crop's camera
    crops.truth.update(
        has_truth=torch.from_numpy(has),
        truth_row=torch.from_numpy(row),
        joints_world=jw,
        joints_cam=jc,
        joints2d=uv[..., :2],
        visible=torch.from_numpy(visible),
        rotmats_cam=torch.where(
            torch.from_numpy(has)[:, None, None, None], rot, torch.eye(3).expand_as(rot)
        ),
        betas=torch.from_numpy(truth.betas[safe]) * torch.from_numpy(has)[:, None],
    )
    return truth


def match_truth_views(
    crops: CropSet, boxes: np.ndarray, scene_dir: str | Path, min_iou: float = 0.3
) -> np.ndarray:
    """Row of `truth/views.parquet` showing the person of each extracted crop, or -1. The person
    is the one the crop's own mask shows: the truth id that most of its mask pixels land on in
    the scene's id masks (`mask_truth_ids`). A crop whose mask lands on nobody is matched per
    (frame, camera) by the overlap of its person box (undistorted image, edges) with the truth
    box (IoU above `min_iou`). Boxes alone gave 9.4 % of crowd_7001's crops another person (a
    person behind someone overlaps the full box of the one in front more than their own).
    Returns (N,) int64."""
    scene_dir = Path(scene_dir)
    if len(boxes) != len(crops):
        raise ValueError(f"boxes has {len(boxes)} rows, the crop set {len(crops)}")
    rig = read_rig(scene_dir / "calibration" / "rig.json", "rig")
    views = read_truth_views(scene_dir)
    v_box = views.full_box.astype(np.float32)  # stored as float32
    shown = mask_truth_ids(crops, scene_dir, rig)
    out = np.full(len(crops), -1, np.int64)
    for i in range(len(crops)):
        cam_name = crops.camera_names[int(crops.camera[i])]
        rows = np.flatnonzero((views.frame == int(crops.frame[i])) & (views.camera == cam_name))
        own = rows[views.person_id[rows] == shown[i]] if shown[i] > 0 else rows[:0]
        if len(own):
            out[i] = own[0]
            continue
        best_iou = min_iou
        cam = rig[cam_name]
        for r in rows:
            # truth boxes are in the distorted image: map their corners to the undistorted one
            x0, y0, x1, y1 = v_box[r]
            corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
            if not np.isfinite(corners).all():
                continue
            xy = cam.undistort_points(corners) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
            tb = np.r_[xy.min(0), xy.max(0)] + 0.5
            iou = float(box_iou(boxes[i], tb)[0, 0])
            if iou > best_iou:
                out[i], best_iou = r, iou
    return out


def mask_truth_ids(
    crops: CropSet,
    scene_dir: str | Path,
    rig,
    step: int = 4,
    min_share: float = 0.5,
    min_partner_share: float = 0.2,
) -> np.ndarray:
    """(N,) the truth person id each crop's mask shows, 0 where it shows nobody clearly.

    Its mask pixels (every `step`-th row and column, mask > 0.5) are taken through the crop's
    camera (K, R, t: undistorted) to the distorted frame, where each lands on a person id or
    on nobody (`mask_hits`). Per (frame, camera) the crops and ids are then paired one-to-one
    (`shown_ids`): a crop whose mask spills onto the person in front of it keeps its own person
    when the front one has a crop of their own (by majority alone, the demo's crop 370 was
    scored against the person in front: 371 mm, 252 against its own)."""
    hits = mask_hits(crops, scene_dir, rig, step)
    keys = list(zip(crops.frame.tolist(), crops.camera.tolist(), strict=True))
    return shown_ids(keys, hits, min_share, min_partner_share)


def mask_hits(crops: CropSet, scene_dir: str | Path, rig, step: int = 4) -> list[np.ndarray]:
    """Per crop, how many of its sampled mask pixels land on each truth id (np.bincount: index
    = person id; id 0, nobody, counts none); empty where the camera has no id masks or the
    mask is empty."""
    scene_dir = Path(scene_dir)
    out = [np.zeros(0, np.int64) for _ in range(len(crops))]
    files: dict[str, IdMaskFile | None] = {}
    try:
        for i in range(len(crops)):
            name = crops.camera_names[int(crops.camera[i])]
            if name not in files:
                path = truth_mask_file(scene_dir, name)
                files[name] = IdMaskFile(path, name) if path.is_file() else None
            ids = files[name].get(int(crops.frame[i])) if files[name] is not None else None
            if ids is None:
                continue
            mask = crops.masks[i, ::step, ::step].numpy() > 0.5
            vv, uu = np.nonzero(mask)
            if len(uu) == 0:
                continue
            px = np.c_[uu * step, vv * step, np.ones(len(uu))]
            rays = px @ np.linalg.inv(crops.K[i].double().numpy()).T  # camera frame, z = 1
            R, t = crops.R[i].double().numpy(), crops.t[i].double().numpy()
            uv = np.round(rig[name].project((rays - t) @ R)).astype(int)
            h, w = ids.shape
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            hit = ids[uv[inside, 1], uv[inside, 0]].astype(np.int64)
            counts = np.bincount(hit)
            counts[:1] = 0  # nobody
            out[i] = counts
    finally:
        for f in files.values():
            if f is not None:
                f.close()
    return out


def shown_ids(
    keys: list[tuple[int, int]],
    hits: list[np.ndarray],
    min_share: float = 0.5,
    min_partner_share: float = 0.2,
) -> np.ndarray:
    """(N,) truth id per crop from its mask hits (`mask_hits`), 0 for nobody. Crops of one key
    (frame, camera) and the ids they hit are paired one-to-one (Hungarian) by the share of each
    crop's hits (shares, not counts: a large crop spilling onto someone must not outweigh that
    person's own small crop); a crop takes its partner when at least `min_partner_share` of its
    hits land on them. A crop left without one (more crops than people there: a duplicate)
    takes the id at least `min_share` of its hits land on, so a duplicate is still scored
    against the person it shows."""
    out = np.zeros(len(hits), np.int64)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, key in enumerate(keys):
        if hits[i].sum() > 0:
            groups.setdefault(key, []).append(i)
    for rows in groups.values():
        width = max(len(hits[i]) for i in rows)
        counts = np.stack([np.pad(hits[i], (0, width - len(hits[i]))) for i in rows])
        totals = counts.sum(1)
        shares = counts / totals[:, None]
        partner = dict(zip(*linear_sum_assignment(-shares), strict=True))
        for a, i in enumerate(rows):
            p = partner.get(a, 0)
            if p > 0 and counts[a, p] >= min_partner_share * totals[a]:
                out[i] = p
            elif counts[a].max() >= min_share * totals[a]:
                out[i] = int(counts[a].argmax())
    return out


def select_rows(crops: CropSet, rows: torch.Tensor | np.ndarray) -> CropSet:
    """A CropSet of the given rows only (truth included), e.g. a train split."""
    r = torch.as_tensor(np.asarray(rows), dtype=torch.long)
    return CropSet(
        images=crops.images[r],
        masks=crops.masks[r],
        K=crops.K[r],
        R=crops.R[r],
        t=crops.t[r],
        camera=crops.camera[r],
        frame=crops.frame[r],
        person=crops.person[r],
        camera_names=list(crops.camera_names),
        truth={k: v[r] for k, v in crops.truth.items()},
        occluders=None if crops.occluders is None else crops.occluders[r],
        anchors=None if crops.anchors is None else crops.anchors[r],
        keypoints=None if crops.keypoints is None else crops.keypoints[r],
        landmarks=None if crops.landmarks is None else crops.landmarks[r],
        distill=None if crops.distill is None else crops.distill.take(r),
    )
