"""Initial camera extrinsics from board views shared between cameras.

Cameras are nodes of a graph; two cameras are linked when they saw the board in the same frames.
Each link's relative pose is a robust average over those frames. Poses are then chained along
the maximum spanning tree (most shared frames first) from a reference camera, so no frame has to
be seen by every camera, only the graph has to be connected. Bundle adjustment refines the
result; this only has to land in its basin of convergence.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationError


class PoseGraphError(CalibrationError):
    """Cameras cannot be placed in one frame (the shared-view graph is not connected)."""


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius norm) to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle(s) between rotations, degrees; broadcasts over leading dimensions."""
    cos = (np.trace(np.swapaxes(Ra, -1, -2) @ Rb, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def robust_mean_pose(
    poses: np.ndarray, weights: np.ndarray | None = None, min_inlier_deg: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Robust average of (N, 4, 4) rigid transforms: chordal mean rotation, then the median
    rotation outliers (above max(3 x median angle, `min_inlier_deg`)) dropped and the mean
    redone; translation is the weighted mean of the inliers. Returns (pose, inlier mask)."""
    poses = np.asarray(poses, dtype=np.float64)
    w = np.ones(len(poses)) if weights is None else np.asarray(weights, dtype=np.float64)
    inl = np.ones(len(poses), dtype=bool)
    R = project_to_rotation(np.einsum("n,nij->ij", w, poses[:, :3, :3]))
    for _ in range(3):
        ang = rotation_angle_deg(R[None], poses[:, :3, :3])
        inl = ang <= max(3.0 * float(np.median(ang)), min_inlier_deg)
        R = project_to_rotation(np.einsum("n,nij->ij", w[inl], poses[inl, :3, :3]))
    t = np.average(poses[inl, :3, 3], axis=0, weights=w[inl])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return out, inl


def invert(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


@dataclass(frozen=True)
class Edge:
    a: str
    b: str
    a_from_b: np.ndarray  # 4x4
    n_frames: int  # frames agreeing with the average


def pairwise_edges(
    views: dict[str, dict[int, np.ndarray]], weights: dict[str, dict[int, float]] | None = None
) -> list[Edge]:
    """Relative poses of every camera pair that shares board frames.

    `views[camera][frame]` is the 4x4 cam_from_board pose of that view; `weights` (e.g. corner
    counts) weight the average."""
    names = list(views)
    edges = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            shared = sorted(set(views[a]) & set(views[b]))
            if not shared:
                continue
            rel = np.stack([views[a][f] @ invert(views[b][f]) for f in shared])
            w = None
            if weights is not None:
                w = np.array([min(weights[a][f], weights[b][f]) for f in shared], dtype=np.float64)
            mean, inl = robust_mean_pose(rel, w)
            edges.append(Edge(a, b, mean, int(inl.sum())))
    return edges


def chain_poses(
    cameras: list[str], edges: list[Edge], reference: str | None = None
) -> tuple[dict[str, np.ndarray], str]:
    """cam_from_ref for every camera, chained along the maximum spanning tree of shared frames.

    Returns (poses, reference). The reference defaults to the best-connected camera."""
    adj: dict[str, list[tuple[int, str, np.ndarray]]] = {c: [] for c in cameras}
    for e in edges:
        adj[e.a].append((e.n_frames, e.b, invert(e.a_from_b)))  # b_from_a
        adj[e.b].append((e.n_frames, e.a, e.a_from_b))  # a_from_b
    if reference is None:
        reference = max(cameras, key=lambda c: sum(n for n, _, _ in adj[c]))
    poses = {reference: np.eye(4)}
    heap = [(-n, nb, reference, T) for n, nb, T in adj[reference]]
    heapq.heapify(heap)
    while heap:
        _, cam, parent, cam_from_parent = heapq.heappop(heap)
        if cam in poses:
            continue
        poses[cam] = cam_from_parent @ poses[parent]
        for n, nb, T in adj[cam]:
            if nb not in poses:
                heapq.heappush(heap, (-n, nb, cam, T))
    missing = [c for c in cameras if c not in poses]
    if missing:
        linked = sorted(poses)
        raise PoseGraphError(
            f"cameras {missing} share no board frame (directly or through other cameras) with "
            f"{linked}; record the board where these cameras and the others see it at the same time"
        )
    return poses, reference
