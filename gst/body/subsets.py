"""Which body vertices carry a Gaussian, and how they split into GST's K token groups.

``vertex_subset`` picks named presets by farthest-point sampling (FPS) on the rest mesh: the
choice is deterministic (it starts from the vertex farthest from the centroid), the ids are
the model's own vertex ids, and smaller presets are prefixes of the same FPS order, so
1723 is a subset of 3445, which is a subset of 6890. Vertices inside the head (Anny's eye
sockets and mouth) are never chosen. For a 6890-vertex SMPL mesh, "6890" is the whole mesh.

``partition_vertices`` splits a subset into K groups of equal size (+-1) that are compact in
space, by recursive balanced bisection.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache

import numpy as np

from gst.body.model import BodyModel, BodyModelData
from gst.body.skeleton import INTERNAL_PART_NAMES

__all__ = ["VERTEX_PRESETS", "vertex_subset", "partition_vertices", "farthest_point_order"]

VERTEX_PRESETS: dict[str, int | None] = {"full": None, "6890": 6890, "3445": 3445, "1723": 1723}


def _surface_candidates(part_labels: np.ndarray, part_names: tuple[str, ...] | None) -> np.ndarray:
    if part_names is None:
        return np.arange(len(part_labels))
    internal = [i for i, name in enumerate(part_names) if name in INTERNAL_PART_NAMES]
    return np.flatnonzero(~np.isin(part_labels, internal))


def farthest_point_order(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` points chosen by Euclidean farthest-point sampling, in the order
    chosen, starting from the point farthest from the centroid (ties: lowest index)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if not 0 < count <= len(points):
        raise ValueError(f"count must lie in [1, {len(points)}], got {count}")
    order = np.empty(count, dtype=np.int64)
    order[0] = int(np.argmax(((points - points.mean(axis=0)) ** 2).sum(axis=1)))
    x, y, z = (np.ascontiguousarray(points[:, k]) for k in range(3))
    nearest = np.full(len(points), np.inf)  # squared distance to the nearest chosen point
    d = np.empty(len(points))
    tmp = np.empty(len(points))
    for i in range(count):
        if i:
            order[i] = int(np.argmax(nearest))
        px, py, pz = points[order[i]]
        np.subtract(x, px, out=d)
        np.multiply(d, d, out=d)
        np.subtract(y, py, out=tmp)
        d += tmp * tmp
        np.subtract(z, pz, out=tmp)
        d += tmp * tmp
        np.minimum(nearest, d, out=nearest)
    return order


@lru_cache(maxsize=16)
def _cached_order(digest: str, count: int, points_bytes: bytes) -> np.ndarray:
    points = np.frombuffer(points_bytes, dtype=np.float64).reshape(-1, 3)
    return farthest_point_order(points, count)


def vertex_subset(model_or_data: BodyModel | BodyModelData, preset: str) -> np.ndarray:
    """Sorted vertex ids of a named preset: "full", "6890", "3445" or "1723".

    "full" is every surface vertex; a numeric preset is that many vertices by FPS on the rest
    mesh (all surface vertices when the mesh has no more than that).
    """
    if preset not in VERTEX_PRESETS:
        raise ValueError(
            f"unknown vertex preset {preset!r}; expected one of {list(VERTEX_PRESETS)}"
        )
    data = model_or_data.data if isinstance(model_or_data, BodyModel) else model_or_data
    candidates = _surface_candidates(np.asarray(data.part_labels), data.part_names)
    count = VERTEX_PRESETS[preset]
    if count is None or count >= len(candidates):
        return candidates.copy()
    # FPS for the largest numeric preset the mesh supports; smaller presets are its prefixes.
    largest = min(max(n for n in VERTEX_PRESETS.values() if n is not None), len(candidates))
    points = np.ascontiguousarray(np.asarray(data.v_template, dtype=np.float64)[candidates])
    digest = hashlib.sha1(points.tobytes()).hexdigest()
    order = _cached_order(digest, largest, points.tobytes())
    return np.sort(candidates[order[:count]])


def _balanced_split(points: np.ndarray, n_left: int, iterations: int = 8) -> np.ndarray:
    """Boolean mask of exactly ``n_left`` points forming one side of a balanced 2-means cut.

    Starts from the principal axis; then alternates centroids and a cut of the points sorted
    by (distance to left centroid)^2 - (distance to right centroid)^2, which is a plane."""
    centred = points - points.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    score = centred @ axis
    mask = np.zeros(len(points), dtype=bool)
    for _ in range(iterations + 1):
        order = np.argsort(score, kind="stable")
        new_mask = np.zeros(len(points), dtype=bool)
        new_mask[order[:n_left]] = True
        if np.array_equal(new_mask, mask):
            break
        mask = new_mask
        c_left, c_right = points[mask].mean(axis=0), points[~mask].mean(axis=0)
        score = ((points - c_left) ** 2).sum(1) - ((points - c_right) ** 2).sum(1)
    return mask


def partition_vertices(rest_vertices: np.ndarray, K: int = 26, seed: int = 0) -> np.ndarray:
    """Group index (0..K-1) of every vertex: K spatially compact groups of equal size (+-1).

    Recursive balanced bisection: each set of vertices meant for k groups is cut by a plane
    (balanced 2-means) into parts for floor(k/2) and ceil(k/2) groups, with point counts in
    exact proportion, until every part is one group. Group sizes are N // K or N // K + 1,
    groups are numbered in cut order (spatial neighbours get nearby numbers). ``seed`` only
    shuffles ties in the cuts; the result is deterministic for given inputs.
    """
    points = np.asarray(rest_vertices, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"rest_vertices must have shape (N, 3), got {points.shape}")
    if not 1 <= K <= len(points):
        raise ValueError(f"K must lie in [1, {len(points)}] for {len(points)} vertices, got {K}")
    rng = np.random.default_rng(seed)
    # Tiny deterministic jitter (1e-9 m) breaks exact ties, e.g. of a mirror-symmetric mesh.
    jittered = points + rng.normal(scale=1e-9, size=points.shape)
    base, extra = divmod(len(points), K)
    sizes = np.full(K, base) + (np.arange(K) < extra)  # group g has sizes[g] vertices
    labels = np.empty(len(points), dtype=np.int64)

    def split(ids: np.ndarray, first: int, k: int) -> None:
        if k == 1:
            labels[ids] = first
            return
        k_left = k // 2
        n_left = int(sizes[first : first + k_left].sum())
        mask = _balanced_split(jittered[ids], n_left)
        split(ids[mask], first, k_left)
        split(ids[~mask], first + k_left, k - k_left)

    split(np.arange(len(points)), 0, K)
    return labels
