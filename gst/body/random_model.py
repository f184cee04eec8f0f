"""A small synthetic body in SMPL layout, for tests and benchmarks that must not need Anny or SMPL.

The skeleton is SMPL's (joint order, parents, a rough T-pose of an adult, metres, Y up, facing
+Z). The mesh is a set of capsule-like tubes around the bones, with proper triangles; skinning
weights blend each tube between its bone's joint and the next; the joint regressor averages the
vertices nearest to each joint; shape and pose blend shapes are smooth random fields. It looks
like nothing in particular, but every array has SMPL's exact layout, so it exercises the whole
code path (including ``posedirs``) at any vertex count, e.g. 6890 like SMPL.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from gst.body.model import BodyModelData
from gst.body.skeleton import (
    NUM_JOINTS,
    PART_NAMES,
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    parts_from_weights,
)

__all__ = ["random_body_data", "ROUGH_TPOSE_JOINTS"]

# A rough adult T-pose (metres), in SMPL joint order; only used to shape the synthetic body.
ROUGH_TPOSE_JOINTS = np.array([
    [0.0, 0.0, 0.0], [0.06, -0.09, 0.0], [-0.06, -0.09, 0.0], [0.0, 0.11, -0.02],
    [0.10, -0.47, 0.0], [-0.10, -0.47, 0.0], [0.0, 0.24, -0.01], [0.09, -0.87, -0.04],
    [-0.09, -0.87, -0.04], [0.0, 0.30, 0.01], [0.11, -0.93, 0.08], [-0.11, -0.93, 0.08],
    [0.0, 0.52, -0.02], [0.07, 0.42, -0.01], [-0.07, 0.42, -0.01], [0.0, 0.59, 0.03],
    [0.17, 0.45, -0.02], [-0.17, 0.45, -0.02], [0.43, 0.44, -0.03], [-0.43, 0.44, -0.03],
    [0.68, 0.44, -0.03], [-0.68, 0.44, -0.03], [0.76, 0.43, -0.04], [-0.76, 0.43, -0.04],
])  # fmt: skip

_LEAF_EXTENSION = {
    "head": 0.18,
    "left_hand": 0.10,
    "right_hand": 0.10,
    "left_foot": 0.08,
    "right_foot": 0.08,
}
_RING = 16


def _radius(name: str) -> float:
    if "spine" in name or name in ("pelvis", "left_hip", "right_hip"):
        return 0.11
    if name in ("left_knee", "right_knee", "neck", "head"):
        return 0.07
    return 0.045


def _tube(
    a: np.ndarray, b: np.ndarray, radius: float, n_len: int, ring: int
) -> tuple[np.ndarray, np.ndarray]:
    """Points on a tube from a to b (n_len rings of `ring` points) and their place t in [0, 1]."""
    axis = b - a
    length = np.linalg.norm(axis)
    u = axis / length
    helper = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    t = (np.arange(n_len) + 0.5) / n_len
    phi = 2 * np.pi * np.arange(ring) / ring
    # Slightly tapered ends so neighbouring tubes do not coincide.
    r = radius * (0.85 + 0.15 * np.sin(np.pi * t))
    pts = (
        a
        + t[:, None, None] * axis
        + r[:, None, None] * (np.cos(phi)[None, :, None] * e1 + np.sin(phi)[None, :, None] * e2)
    )
    return pts.reshape(-1, 3), np.repeat(t, ring)


def _tube_faces(first: int, n_len: int, ring: int) -> np.ndarray:
    faces = []
    for i in range(n_len - 1):
        for k in range(ring):
            a, b = first + i * ring + k, first + i * ring + (k + 1) % ring
            c, d = a + ring, b + ring
            faces += [(a, c, b), (b, c, d)]
    return np.array(faces, dtype=np.int64).reshape(-1, 3)


def _rings_per_tube(lengths: np.ndarray, total: int) -> np.ndarray:
    """Rings per tube, about proportional to length, at least 2 each, summing to `total` (the
    last tube loses at most a partial ring to the exact vertex count)."""
    n = np.maximum(2, np.floor(lengths * total / lengths.sum()).astype(int))
    while n.sum() > total:  # the minimum of 2 took rings from the budget: the longest give back
        n[np.argmax(np.where(n > 2, lengths / n, -1.0))] -= 1
    while n.sum() < total:  # the coarsest tubes get the rings left over
        n[np.argmax(lengths / n)] += 1
    return n


def random_body_data(
    num_vertices: int = 6890, num_betas: int = 10, with_posedirs: bool = True, seed: int = 0
) -> BodyModelData:
    """A synthetic SMPL-layout body with exactly ``num_vertices`` vertices (>= 400).

    Every tube gets at least two rings, whatever the count: small bodies get thinner rings
    (down to 7 points at 400) rather than losing the tubes listed last (arms, hands, head),
    whose joints would then carry no skin weight at all."""
    if num_vertices < 400:
        raise ValueError(f"num_vertices must be at least 400, got {num_vertices}")
    rng = np.random.default_rng(seed)
    joints = ROUGH_TPOSE_JOINTS
    # One tube per bone (parent -> child, skinned to the parent) and one past each leaf.
    bones = [(SMPL_PARENTS[j], j) for j in range(1, NUM_JOINTS)]
    ends = [(joints[p], joints[c], p, c) for p, c in bones]
    for name, ext in _LEAF_EXTENSION.items():
        j = SMPL_JOINT_NAMES.index(name)
        direction = joints[j] - joints[SMPL_PARENTS[j]]
        ends.append((joints[j], joints[j] + ext * direction / np.linalg.norm(direction), j, j))
    lengths = np.array([np.linalg.norm(b - a) for a, b, _, _ in ends])
    ring = min(_RING, num_vertices // (2 * len(ends)))
    n_len = _rings_per_tube(lengths, -(-num_vertices // ring))

    points, owner, child, pos, faces = [], [], [], [], []
    count = 0
    for (a, b, p, c), n in zip(ends, n_len, strict=True):
        pts, t = _tube(a, b, _radius(SMPL_JOINT_NAMES[c]), int(n), ring)
        faces.append(_tube_faces(count, int(n), ring))
        points.append(pts)
        owner += [p] * len(pts)
        child += [c] * len(pts)
        pos.append(t)
        count += len(pts)
    v = np.concatenate(points)[:num_vertices]
    owner, child = np.array(owner)[:num_vertices], np.array(child)[:num_vertices]
    t = np.concatenate(pos)[:num_vertices]
    faces = np.concatenate(faces)
    faces = faces[(faces < num_vertices).all(axis=1)]

    # Weights: the bone's joint, blending into the child joint over the last quarter.
    blend = np.clip((t - 0.75) / 0.25, 0.0, 1.0) * 0.5
    weights = np.zeros((num_vertices, NUM_JOINTS))
    weights[np.arange(num_vertices), owner] += 1.0 - blend
    weights[np.arange(num_vertices), child] += blend

    # Regressor: the mean of the 12 vertices nearest each joint.
    rows, cols = [], []
    for j in range(NUM_JOINTS):
        near = np.argsort(np.linalg.norm(v - joints[j], axis=1))[:12]
        rows += [j] * len(near)
        cols += near.tolist()
    regressor = scipy.sparse.csr_matrix(
        (np.full(len(rows), 1.0 / 12), (rows, cols)), shape=(NUM_JOINTS, num_vertices)
    )

    # Shape: overall scale, girth, then smooth random fields (about a centimetre per beta).
    centre = v.mean(axis=0)
    shapedirs = np.zeros((num_vertices, 3, num_betas))
    shapedirs[:, :, 0] = 0.05 * (v - centre)
    radial = v - joints[owner]
    shapedirs[:, :, min(1, num_betas - 1)] += 0.1 * radial
    for b in range(2, num_betas):
        lin = rng.normal(size=(3, 3)) * 0.01
        shapedirs[:, :, b] = (v - centre) @ lin + 0.003 * np.sin(v @ rng.normal(size=(3, 3)) * 6.0)
    posedirs = (
        rng.normal(scale=2e-3, size=(9 * (NUM_JOINTS - 1), 3 * num_vertices))
        if with_posedirs
        else None
    )

    return BodyModelData(
        v_template=v,
        shapedirs=shapedirs,
        J_regressor=regressor,
        weights=weights,
        parents=np.array(SMPL_PARENTS),
        faces=faces,
        joint_names=SMPL_JOINT_NAMES,
        part_labels=parts_from_weights(weights, SMPL_JOINT_NAMES),
        part_names=PART_NAMES,
        posedirs=posedirs,
        name=f"random-{num_vertices}",
        source=f"gst.body.random_model seed {seed}",
        licence="synthetic (no licence restrictions)",
    ).validate()
