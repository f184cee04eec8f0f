"""Person crops with exact truth from a rendered synthetic scene (docs/formats/synth_scene.md).

Used for supervised pretraining (the stand-in for HMR2's 3D-labelled start) and to measure
MPJPE on scenes with truth. Crops follow the tracking/extraction convention (HMR2 square box,
undistorted, own K) via `gst.track.view.TrackingView`, so a model sees the same kind of input
at pretraining, training and tracking time.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pyarrow.parquet as pq
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from calibration.formats import read_rig
from gst.metrics.image import box_iou
from gst.track.view import TrackingView
from gst.train.views import CropSet


def _column(table, name: str, width: int) -> np.ndarray:
    return np.asarray(
        table.column(name).combine_chunks().flatten().to_numpy(zero_copy_only=False)
    ).reshape(-1, width)


def _read_video(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise OSError(f"cannot open video {path}")
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    if not frames:
        raise OSError(f"video {path} has no readable frame")
    return frames


def crops_from_synth_scene(
    scene_dir: str | Path,
    crop_size: int = 256,
    frame_stride: int = 1,
    min_mask_area: int = 200,
    min_visible_joints: int = 8,
    cameras: list[str] | None = None,
    progress=None,
) -> CropSet:
    """All (frame, person, camera) crops of a synthetic scene with their truth.

    truth keys: joints_world (N,24,3), joints_cam (N,24,3), joints2d (N,24,2) crop px,
    visible (N,24), rotmats_cam (N,24,3,3) (index 0 = global orientation in the crop's camera),
    betas (N, nb), person_truth_id (N,).
    """
    scene_dir = Path(scene_dir)
    rig = read_rig(scene_dir / "calibration" / "rig.json", "rig")
    views = pq.read_table(scene_dir / "truth" / "views.parquet")
    people = pq.read_table(scene_dir / "truth" / "people.parquet")
    nb = people.schema.field("betas").type.list_size
    p_frame = people.column("frame").to_numpy()
    p_id = people.column("person_id").to_numpy()
    p_index = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(p_frame, p_id, strict=True))}
    joints_world_all = _column(people, "joints3d", 72).reshape(-1, 24, 3).astype(np.float64)
    go = _column(people, "global_orient", 3)
    bp = _column(people, "body_pose", 69).reshape(-1, 23, 3)
    betas_all = _column(people, "betas", nb)

    v_frame = views.column("frame").to_numpy()
    v_pid = views.column("person_id").to_numpy()
    v_cam = np.asarray(views.column("camera").to_pylist())
    boxes = np.stack([views.column(k).to_numpy() for k in ("x0", "y0", "x1", "y1")], axis=1).astype(
        np.float64
    )
    area = views.column("mask_area").to_numpy()
    visible = _column(views, "visible", 24).astype(bool)

    names = cameras or rig.names
    out = {
        k: []
        for k in (
            "images",
            "masks",
            "K",
            "R",
            "t",
            "camera",
            "frame",
            "person",
            "joints_world",
            "joints_cam",
            "joints2d",
            "visible",
            "rotmats_cam",
            "betas",
        )
    }
    cam_iter = (
        progress(names, description="synthetic crops", total=len(names)) if progress else names
    )
    for ci, name in enumerate(cam_iter):
        cam = rig[name]
        view = TrackingView.for_video(cam.width, cam.height, cam, video=name)
        frames = _read_video(scene_dir / "videos" / f"{name}.mp4")
        with h5py.File(scene_dir / "truth" / "masks" / f"{name}.h5", "r") as f:
            masks = f["mask"][:]
        rows = np.flatnonzero(
            (v_cam == name)
            & (area >= min_mask_area)
            & np.isfinite(boxes).all(1)
            & (visible.sum(1) >= min_visible_joints)
            & (v_frame % frame_stride == 0)
        )
        for r in rows:
            fr, pid = int(v_frame[r]), int(v_pid[r])
            if fr >= len(frames):
                continue
            window = view.window(boxes[r] + 0.5, crop_size)  # truth boxes: pixel-centre edges
            img, K_crop = view.crop(frames[fr], window)
            person_mask = np.repeat((masks[fr] == pid).astype(np.uint8)[..., None] * 255, 3, axis=2)
            mask_crop, _ = view.crop(person_mask, window)
            k = p_index[(fr, pid)]
            jw = joints_world_all[k]
            jc = jw @ cam.R.T + cam.t
            uv = jc[:, :2] / jc[:, 2:] * [K_crop[0, 0], K_crop[1, 1]] + [K_crop[0, 2], K_crop[1, 2]]
            out["images"].append(img)
            out["masks"].append(mask_crop[..., 0].astype(np.float32) / 255.0)
            out["K"].append(K_crop)
            out["R"].append(cam.R)
            out["t"].append(cam.t)
            out["camera"].append(ci)
            out["frame"].append(fr)
            out["person"].append(pid)
            out["joints_world"].append(jw)
            out["joints_cam"].append(jc)
            out["joints2d"].append(uv)
            out["visible"].append(visible[r])
            out["rotmats_cam"].append(np.concatenate([go[k][None], bp[k]]))
            out["betas"].append(betas_all[k])
    if not out["images"]:
        raise ValueError(
            f"{scene_dir}: no person crop passed the filters (min_mask_area={min_mask_area}, "
            f"min_visible_joints={min_visible_joints})"
        )
    t = {k: torch.as_tensor(np.stack(v)) for k, v in out.items()}
    aa = t["rotmats_cam"].reshape(-1, 3).float()
    rot = axis_angle_to_rotation_matrix(aa).reshape(-1, 24, 3, 3)
    R = t["R"].float()
    rot[:, 0] = R @ rot[:, 0]  # global orientation: body -> world, then world -> this camera
    truth = {
        "joints_world": t["joints_world"].float(),
        "joints_cam": t["joints_cam"].float(),
        "joints2d": t["joints2d"].float(),
        "visible": t["visible"].float(),
        "rotmats_cam": rot,
        "betas": t["betas"].float(),
        "person_truth_id": t["person"].long(),
    }
    return CropSet(
        images=t["images"].to(torch.uint8),
        masks=t["masks"].float(),
        K=t["K"].float(),
        R=R,
        t=t["t"].float(),
        camera=t["camera"].long(),
        frame=t["frame"].long(),
        person=t["person"].long(),
        camera_names=list(names),
        truth=truth,
    )


def scene_fps(scene_dir: str | Path) -> float:
    return float(json.loads((Path(scene_dir) / "scene.json").read_text())["fps"])


def match_truth_views(
    crops: CropSet, boxes: np.ndarray, scene_dir: str | Path, min_iou: float = 0.3
) -> np.ndarray:
    """Row of `truth/views.parquet` showing the person of each extracted crop, or -1: matched per
    (frame, camera) by the overlap of the crop's person box (undistorted image, edges) with the
    truth box (IoU above `min_iou`). Returns (N,) int64."""
    scene_dir = Path(scene_dir)
    if len(boxes) != len(crops):
        raise ValueError(f"boxes has {len(boxes)} rows, the crop set {len(crops)}")
    rig = read_rig(scene_dir / "calibration" / "rig.json", "rig")
    views = pq.read_table(scene_dir / "truth" / "views.parquet")
    v_frame = views.column("frame").to_numpy()
    v_cam = np.asarray(views.column("camera").to_pylist())
    v_box = np.stack(
        [views.column(k).to_numpy() for k in ("full_x0", "full_y0", "full_x1", "full_y1")], 1
    )
    out = np.full(len(crops), -1, np.int64)
    for i in range(len(crops)):
        cam_name = crops.camera_names[int(crops.camera[i])]
        rows = np.flatnonzero((v_frame == int(crops.frame[i])) & (v_cam == cam_name))
        best_iou = min_iou
        cam = rig[cam_name]
        for r in rows:
            # truth boxes are in the distorted image: map their corners to the undistorted one
            corners = np.array(
                [
                    [v_box[r, 0], v_box[r, 1]],
                    [v_box[r, 2], v_box[r, 1]],
                    [v_box[r, 0], v_box[r, 3]],
                    [v_box[r, 2], v_box[r, 3]],
                ]
            )
            if not np.isfinite(corners).all():
                continue
            xy = cam.undistort_points(corners) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
            tb = np.r_[xy.min(0), xy.max(0)] + 0.5
            iou = float(box_iou(boxes[i], tb)[0, 0])
            if iou > best_iou:
                out[i], best_iou = r, iou
    return out
