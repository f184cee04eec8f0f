"""A small synthetic multi-camera capture for the fuse tests: known bodies, cameras on a ring,
the bodies' virtual markers projected (plus noise) as per-crop landmarks, in a real crop store."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from calibration.camera import Camera, Rig, look_at_rotation
from gst.body import load_body_model
from gst.body.joint_limits import sample_body_pose
from gst.body.markers import MarkerModel
from gst.body.rotations import matrix_to_axis_angle
from gst.data.store import CropBatch, CropStore, CropStoreWriter
from gst.fuse.observations import PersonObservations

S = 32  # crop images are dummies; K_crop is the camera's own K


@dataclass
class Capture:
    rig: Rig
    betas: np.ndarray  # (P, 10)
    body_pose: np.ndarray  # (P, T, 23, 3)
    global_orient: np.ndarray  # (P, T, 3)
    transl: np.ndarray  # (P, T, 3)
    joints: np.ndarray  # (P, T, 24, 3)
    markers: np.ndarray  # (P, T, 33, 3)


def make_rig(n_cams: int = 4) -> Rig:
    cams = []
    for c in range(n_cams):
        a = 2 * np.pi * c / n_cams + 0.3
        pos = np.array([5 * np.cos(a), 5 * np.sin(a), 2.0])
        R = look_at_rotation(pos, np.array([0.0, 0.0, 1.0]))
        K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
        cams.append(Camera.create(f"cam{c}", K, [], R, -R @ pos, 640, 480))
    return Rig(cams)


def make_capture(body, n_people=2, n_frames=6, n_cams=4, seed=0) -> Capture:
    g = torch.Generator().manual_seed(seed)
    markers = MarkerModel.load()
    P, T = n_people, n_frames
    betas = torch.randn(P, 10, generator=g, dtype=torch.float64) * 0.7
    # a smooth motion per person: interpolate between two random poses
    p0 = matrix_to_axis_angle(sample_body_pose(P, g, scale=0.4, dtype=torch.float64))
    p1 = matrix_to_axis_angle(sample_body_pose(P, g, scale=0.4, dtype=torch.float64))
    s = torch.linspace(0, 1, T, dtype=torch.float64)[None, :, None, None]
    pose = p0[:, None] * (1 - s) + p1[:, None] * s  # (P, T, 23, 3)
    yaw = torch.rand(P, generator=g, dtype=torch.float64) * 6.28
    # body (SMPL axes, y up) -> world (z up): x -> x, y -> z, z -> -y, then a yaw about z
    base = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)
    go, tr = [], []
    for k in range(P):
        c, sn = torch.cos(yaw[k]), torch.sin(yaw[k])
        Rz = torch.tensor([[c, -sn, 0], [sn, c, 0], [0, 0, 1]], dtype=torch.float64)
        go.append(matrix_to_axis_angle((Rz @ base)[None].expand(T, 3, 3)))
        start = torch.tensor([1.4 * k - 0.7, 0.0, 0.95], dtype=torch.float64)
        tr.append(
            start
            + torch.linspace(0, 0.3, T, dtype=torch.float64)[:, None] * torch.tensor([1.0, 0.5, 0])
        )
    go, tr = torch.stack(go), torch.stack(tr)
    with torch.no_grad():
        out = body(
            betas.repeat_interleave(T, 0), pose.reshape(P * T, 23, 3), go.reshape(P * T, 3),
            tr.reshape(P * T, 3), vertex_ids=markers.vertex_ids, return_transforms=True,
        )  # fmt: skip
    X = markers.positions(out).double().numpy().reshape(P, T, 33, 3)
    return Capture(
        make_rig(n_cams), betas.numpy(), pose.numpy(), go.numpy(), tr.numpy(),
        out.joints.double().numpy().reshape(P, T, 24, 3), X,
    )  # fmt: skip


def project(rig: Rig, X: np.ndarray) -> np.ndarray:
    """(..., 33, 3) -> (..., C, 33, 2) through every camera (no distortion)."""
    return np.stack(
        [rig[c].project(X.reshape(-1, 3)).reshape(*X.shape[:-1], 2) for c in rig.names], -3
    )


def observations(cap: Capture, noise_px=0.0, seed=0) -> list[PersonObservations]:
    rng = np.random.default_rng(seed)
    P, T = cap.markers.shape[:2]
    C = len(cap.rig)
    out = []
    for k in range(P):
        uv = project(cap.rig, cap.markers[k]) + rng.normal(0, noise_px, (T, C, 33, 2))
        out.append(
            PersonObservations(
                k + 1,
                np.arange(T),
                uv,
                np.ones((T, C, 33)),
                np.broadcast_to(np.stack([c.K for c in cap.rig]), (T, C, 3, 3)).copy(),
                np.broadcast_to(np.stack([np.c_[c.R, c.t] for c in cap.rig]), (T, C, 3, 4)).copy(),
                np.ones((T, C)),
                np.arange(T * C).reshape(T, C),
            )  # fmt: skip
        )
    return out


def write_store(
    path: Path, cap: Capture, noise_px=0.5, seed=0, with_landmarks: bool = False
) -> np.ndarray:
    """A complete crop store of every (frame, person, camera); returns its landmarks (N, 33, 3),
    which `with_landmarks` also stores in it (as the extraction does)."""
    rng = np.random.default_rng(seed)
    P, T = cap.markers.shape[:2]
    rows, lms = [], []
    for f in range(T):
        for k in range(P):
            uv = project(cap.rig, cap.markers[k, f])
            for c, cam in enumerate(cap.rig):
                rows.append((f, k + 1, c, cam))
                conf = np.full((33, 1), 0.9)
                lms.append(np.c_[uv[c] + rng.normal(0, noise_px, (33, 2)), conf])
    n = len(rows)
    batch = CropBatch(
        images=np.zeros((n, S, S, 3), np.uint8),
        masks=np.zeros((n, S, S), np.uint8),
        K_crop=np.stack([r[3].K for r in rows]),
        R=np.stack([r[3].R for r in rows]),
        t=np.stack([r[3].t for r in rows]),
        box=np.zeros((n, 4)),
        crop_box=np.tile([0.0, 0.0, float(S)], (n, 1)),  # side = S: crop px = reported px
        camera=np.array([r[2] for r in rows], np.int32),
        frame=np.array([r[0] for r in rows], np.int64),
        person_id=np.array([r[1] for r in rows], np.int64),
        mask_support=np.full(n, np.nan, np.float32),
        landmarks=np.stack(lms).astype(np.float32) if with_landmarks else None,
    )
    with CropStoreWriter(path, cap.rig.names, S, landmarks=with_landmarks) as w:
        w.commit(batch, [(f, c) for f in range(T) for c in range(len(cap.rig))])
        w.finalize({"n_frames": T})
    return np.stack(lms).astype(np.float32)


def capture_in_store(folder: Path, **capture) -> tuple[Capture, np.ndarray]:
    """A capture of the open body model (`make_capture(**capture)`) written to folder/crops.h5;
    the capture and the store's landmarks."""
    cap = make_capture(load_body_model("anny"), **capture)
    return cap, write_store(folder / "crops.h5", cap)


def windows_store(path, windows, masks, camera, frame, images=None, names=("a", "b")) -> CropStore:
    """A crop store of square crops: each row's window (x0, y0, side) in its camera's image, its
    person mask, camera index and frame (person ids 1, 2, ...); images black unless given."""
    n, size = len(windows), np.asarray(masks).shape[1]
    batch = CropBatch(
        images=np.zeros((n, size, size, 3), np.uint8)
        if images is None
        else np.asarray(images, np.uint8),
        masks=np.asarray(masks, np.uint8),
        K_crop=np.tile(np.eye(3), (n, 1, 1)),
        R=np.tile(np.eye(3), (n, 1, 1)),
        t=np.zeros((n, 3)),
        box=np.zeros((n, 4)),
        crop_box=np.asarray(windows, np.float64),
        camera=np.asarray(camera, np.int32),
        frame=np.asarray(frame, np.int64),
        person_id=np.arange(1, n + 1),
        mask_support=np.full(n, np.nan, np.float32),
    )
    with CropStoreWriter(path, list(names), size) as w:
        w.commit(batch, sorted({(int(f), int(c)) for f, c in zip(frame, camera, strict=True)}))
        w.finalize({"n_frames": int(max(frame)) + 1})
    return CropStore(path)
