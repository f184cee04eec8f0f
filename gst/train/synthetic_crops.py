"""Person crops with exact truth from a rendered synthetic scene (docs/formats/synth_scene.md).

Used for supervised pretraining (the stand-in for HMR2's 3D-labelled start) and to measure
MPJPE on scenes with truth. Crops follow the tracking/extraction convention (HMR2 square box,
undistorted, own K) via `gst.data.camera_view.TrackingView`, so a model sees the same kind of input
at pretraining, training and tracking time.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from calibration.formats import read_rig
from gst.data.camera_view import TrackingView
from gst.train.views import CropSet
from gst.video import VideoError, iter_frames
from synth.truth import read_scene_truth, read_truth_views, truth_mask_file

log = logging.getLogger("gst.train")


def _read_video(path: Path) -> list[np.ndarray]:
    frames = [cv2.cvtColor(f.image, cv2.COLOR_BGR2RGB) for f in iter_frames(path)]
    if not frames:
        raise VideoError(f"video {path} has no readable frame")
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
    views = read_truth_views(scene_dir)
    people = read_scene_truth(scene_dir)
    p_index = people.row_index()
    joints_world_all = people.joints_world.astype(np.float64)
    go, bp, betas_all = people.global_orient, people.body_pose, people.betas
    v_frame, v_pid, v_cam = views.frame, views.person_id, views.camera
    boxes, area, visible = views.box, views.mask_area, views.visible

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
        with h5py.File(truth_mask_file(scene_dir, name), "r") as f:
            masks = f["mask"][:]
        rows = np.flatnonzero(
            (v_cam == name)
            & (area >= min_mask_area)
            & np.isfinite(boxes).all(1)
            & (visible.sum(1) >= min_visible_joints)
            & (v_frame % frame_stride == 0)
        )
        past = rows[v_frame[rows] >= len(frames)]
        if len(past):  # a video cut short (a copy interrupted): its truth views were dropped
            log.warning(
                "%s: camera %s's video holds %d frames, its truth views run to frame %d: %d "
                "views past the video's end are left out",
                scene_dir, name, len(frames), int(v_frame[past].max()), len(past),
            )  # fmt: skip
            rows = rows[v_frame[rows] < len(frames)]
        for r in rows:
            fr, pid = int(v_frame[r]), int(v_pid[r])
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
