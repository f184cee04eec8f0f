"""Pose a body model along a motion clip and place it in the world with its feet on the floor.

The written truth is exactly what the body model gives for the written parameters:
`model(betas, body_pose, global_orient, transl)` reproduces the world vertices and joints, with
global_orient including the SMPL-to-world rotation and the heading (see `synth.world`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from synth.motions import MotionClip
from synth.skeleton import NUM_JOINTS, local_rotations, rest_corrections
from synth.world import heading_rotation


@dataclass(frozen=True)
class PersonTrack:
    """One person's posed sequence. Arrays are float32; world frame, metres."""

    person_id: int
    betas: np.ndarray  # (nb,)
    global_orient: np.ndarray  # (T, 3) axis-angle, SMPL axes -> world
    body_pose: np.ndarray  # (T, 23, 3) axis-angle, model-space local rotations
    transl: np.ndarray  # (T, 3)
    joints: np.ndarray  # (T, 24, 3) world
    vertices: np.ndarray  # (T, V, 3) world
    labels: tuple[str, ...]  # per-frame motion name
    rest_vertices: np.ndarray  # (V, 3) zero pose, SMPL axes (for appearance)
    rest_joints: np.ndarray  # (24, 3) zero pose, SMPL axes

    @property
    def n_frames(self) -> int:
        return len(self.labels)


def check_body_model(model) -> None:
    """Raise a clear error if `model` lacks what synth needs."""
    missing = [a for a in ("faces", "num_betas", "joint_names") if not hasattr(model, a)]
    if missing:
        raise TypeError(
            f"body model {type(model).__name__} lacks {missing}; expected the gst.body API"
        )
    if len(model.joint_names) != NUM_JOINTS:
        raise ValueError(
            f"body model has {len(model.joint_names)} joints, expected {NUM_JOINTS} (SMPL layout)"
        )
    faces = np.asarray(model.faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"body model faces have shape {faces.shape}, expected (F, 3)")


def run_body_model(
    model,
    betas: np.ndarray,
    body_pose: np.ndarray,
    global_orient: np.ndarray,
    transl: np.ndarray,
    batch: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate the model on (T, ...) float32 arrays in batches; returns vertices, joints."""
    T = len(body_pose)
    verts, joints = [], []
    with torch.no_grad():
        for s in range(0, T, batch):
            e = min(T, s + batch)
            out = model(
                betas=torch.from_numpy(np.repeat(betas[None], e - s, axis=0)),
                body_pose=torch.from_numpy(body_pose[s:e]),
                global_orient=torch.from_numpy(global_orient[s:e]),
                transl=torch.from_numpy(transl[s:e]),
            )
            verts.append(out.vertices.detach().to(torch.float32).numpy())
            joints.append(out.joints.detach().to(torch.float32).numpy()[:, :NUM_JOINTS])
    return np.concatenate(verts), np.concatenate(joints)


def rest_pose(model, betas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-pose vertices and joints (SMPL axes) for one shape."""
    z = np.zeros((1, 23, 3), np.float32)
    v, j = run_body_model(
        model,
        betas.astype(np.float32),
        z,
        np.zeros((1, 3), np.float32),
        np.zeros((1, 3), np.float32),
    )
    return v[0], j[0]


FLOOR_TOLERANCE = 0.005  # metres a body may dip below the floor after temporal smoothing
FLOAT_TOLERANCE = 0.008  # metres a grounded body may float after temporal smoothing


def floor_offset(required: np.ndarray, fps: float, smooth: bool = True) -> np.ndarray:
    """Vertical offset per frame from the offset that puts the lowest point on the floor.

    The lowest point switches between vertices (heel, toe, the other foot), which puts kinks in
    `required`; a 40 ms Gaussian removes them. Smooth corrections then pull the result back into
    [required - FLOOR_TOLERANCE, required + FLOAT_TOLERANCE], so contact stays within millimetres.
    """
    if not smooth or len(required) < 3:
        return required
    sigma = 0.04 * fps
    z = gaussian_filter1d(required, sigma=sigma, mode="nearest")
    for _ in range(50):
        low = np.clip(required - FLOOR_TOLERANCE - z, 0, None)
        high = np.clip(z - required - FLOAT_TOLERANCE, 0, None)
        if max(low.max(), high.max()) < 1e-5:
            break
        z = z + 1.5 * gaussian_filter1d(low - high, sigma=sigma, mode="nearest")
    return np.clip(z, required - FLOOR_TOLERANCE, None)


def pose_person(model, betas: np.ndarray, clip: MotionClip, person_id: int) -> PersonTrack:
    """Pose `model` with shape `betas` along `clip` and put the lowest point on the floor.

    Vertical translation puts the lowest vertex at z = clip.lift (0 when grounded), smoothed in
    time (`floor_offset`), so no body part goes more than FLOOR_TOLERANCE below the floor and
    supporting feet touch it.
    """
    check_body_model(model)
    betas = np.asarray(betas, dtype=np.float32).ravel()
    if betas.size != model.num_betas:
        raise ValueError(
            f"person {person_id}: betas has {betas.size} values, the body model expects "
            f"{model.num_betas}"
        )
    rest_v, rest_j = rest_pose(model, betas)
    C = rest_corrections(rest_j)
    T = clip.n_frames
    authored = (
        Rotation.from_euler("XYZ", clip.angles.reshape(-1, 3))
        .as_matrix()
        .reshape(T, NUM_JOINTS, 3, 3)
    )
    local = local_rotations(authored, C)
    root = heading_rotation(clip.heading) @ authored[:, 0]
    body_pose = (
        Rotation.from_matrix(local[:, 1:].reshape(-1, 3, 3))
        .as_rotvec()
        .reshape(T, 23, 3)
        .astype(np.float32)
    )
    global_orient = Rotation.from_matrix(root).as_rotvec().astype(np.float32)
    v0, j0 = run_body_model(model, betas, body_pose, global_orient, np.zeros((T, 3), np.float32))
    transl = np.zeros((T, 3))
    transl[:, :2] = clip.position - j0[:, 0, :2]
    transl[:, 2] = floor_offset(clip.lift - v0[..., 2].min(axis=1), clip.fps, clip.smooth)
    transl = transl.astype(np.float32)
    verts, joints = run_body_model(model, betas, body_pose, global_orient, transl)
    return PersonTrack(
        person_id=person_id,
        betas=betas,
        global_orient=global_orient,
        body_pose=body_pose,
        transl=transl,
        joints=joints,
        vertices=verts,
        labels=clip.labels,
        rest_vertices=rest_v,
        rest_joints=rest_j,
    )
