"""The SMPL 24-joint skeleton and the body-part vocabulary shared by every body model here.

Joint order and parents are SMPL's (the order of its ``kintree_table``), so pose tensors move
between models and tools unchanged. Body parts are coarser than joints; every model labels its
vertices with the same part names, so part-wise metrics and synthetic clothing work on any body.
"""

from __future__ import annotations

import numpy as np

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)  # fmt: skip

SMPL_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)  # fmt: skip

NUM_JOINTS = 24

# Body parts. The last ones are inside the head (Anny models the eye sockets and mouth); they
# exist in the mesh but carry no Gaussians by default and no clothing.
PART_NAMES: tuple[str, ...] = (
    "head", "neck", "torso", "pelvis",
    "left_upper_arm", "right_upper_arm", "left_forearm", "right_forearm",
    "left_hand", "right_hand", "left_thigh", "right_thigh", "left_shin", "right_shin",
    "left_foot", "right_foot", "left_eye", "right_eye", "eye_cavity", "mouth_cavity",
)  # fmt: skip

INTERNAL_PART_NAMES: frozenset[str] = frozenset({"eye_cavity", "mouth_cavity"})

# The part a vertex belongs to when it is labelled by its dominant skinning joint.
JOINT_TO_PART: dict[str, str] = {
    "pelvis": "pelvis", "left_hip": "left_thigh", "right_hip": "right_thigh",
    "spine1": "torso", "spine2": "torso", "spine3": "torso",
    "left_knee": "left_shin", "right_knee": "right_shin",
    "left_ankle": "left_foot", "right_ankle": "right_foot",
    "left_foot": "left_foot", "right_foot": "right_foot",
    "neck": "neck", "head": "head", "left_collar": "torso", "right_collar": "torso",
    "left_shoulder": "left_upper_arm", "right_shoulder": "right_upper_arm",
    "left_elbow": "left_forearm", "right_elbow": "right_forearm",
    "left_wrist": "left_hand", "right_wrist": "right_hand",
    "left_hand": "left_hand", "right_hand": "right_hand",
}  # fmt: skip


def parts_from_weights(weights: np.ndarray, joint_names: tuple[str, ...] | list[str]) -> np.ndarray:
    """Per-vertex part index (into PART_NAMES) from each vertex's dominant skinning joint.

    Joints whose name is not an SMPL joint name raise a ValueError (the part table is SMPL's).
    """
    unknown = [n for n in joint_names if n not in JOINT_TO_PART]
    if unknown:
        raise ValueError(f"no body part known for joints {unknown}; expected SMPL joint names")
    joint_part = np.array([PART_NAMES.index(JOINT_TO_PART[n]) for n in joint_names])
    return joint_part[np.asarray(weights).argmax(axis=1)].astype(np.int64)


def kinematic_levels(parents: np.ndarray | list[int]) -> list[np.ndarray]:
    """Joints grouped by depth in the tree: level 0 is the root, level d the joints whose parent
    is in level d-1. Lets forward kinematics take one batched product per level."""
    parents = np.asarray(parents)
    depth = np.zeros(len(parents), dtype=np.int64)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1)]
