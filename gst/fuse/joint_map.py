"""Which BlazePose landmarks observe which body-model joint (SMPL order).

The fit itself uses every landmark through the virtual markers (gst.body.markers); this table
only says, per output joint, which landmarks carry its 2D evidence: a joint's view count is
that of its least-seen landmark (each landmark is triangulated from its own views), its camera
mask the cameras that used any of them, its reprojection error the mean over those landmarks,
and a joint whose least-seen landmark has fewer than 2 views in a frame is flagged gap-filled
(gst.fuse.tables.joint_evidence; docs/formats/fused_bodies.md).
Joints without a landmark (spine1-3, neck, collars) come from the body model alone.

| joint | landmarks |
| --- | --- |
| pelvis | left_hip, right_hip |
| left_hip / right_hip | left_hip / right_hip |
| left_knee / right_knee | left_knee / right_knee |
| left_ankle / right_ankle | left_ankle / right_ankle |
| left_foot / right_foot | heel and foot_index of that side |
| head | nose, left_ear, right_ear |
| left_shoulder / right_shoulder | left_shoulder / right_shoulder |
| left_elbow / right_elbow | left_elbow / right_elbow |
| left_wrist / right_wrist | left_wrist / right_wrist |
| left_hand / right_hand | pinky, index and thumb of that side |
"""

from __future__ import annotations

from gst.body.markers import BLAZEPOSE_NAMES
from gst.body.skeleton import SMPL_JOINT_NAMES

__all__ = ["JOINT_LANDMARKS", "joint_landmark_indices"]

JOINT_LANDMARKS: dict[str, tuple[str, ...]] = {
    "pelvis": ("left_hip", "right_hip"),
    "left_hip": ("left_hip",),
    "right_hip": ("right_hip",),
    "left_knee": ("left_knee",),
    "right_knee": ("right_knee",),
    "left_ankle": ("left_ankle",),
    "right_ankle": ("right_ankle",),
    "left_foot": ("left_heel", "left_foot_index"),
    "right_foot": ("right_heel", "right_foot_index"),
    "head": ("nose", "left_ear", "right_ear"),
    "left_shoulder": ("left_shoulder",),
    "right_shoulder": ("right_shoulder",),
    "left_elbow": ("left_elbow",),
    "right_elbow": ("right_elbow",),
    "left_wrist": ("left_wrist",),
    "right_wrist": ("right_wrist",),
    "left_hand": ("left_pinky", "left_index", "left_thumb"),
    "right_hand": ("right_pinky", "right_index", "right_thumb"),
}


def joint_landmark_indices() -> list[list[int]]:
    """Per SMPL joint (24, in order), the indices of its landmarks (empty: model only)."""
    return [
        [BLAZEPOSE_NAMES.index(n) for n in JOINT_LANDMARKS.get(j, ())] for j in SMPL_JOINT_NAMES
    ]
