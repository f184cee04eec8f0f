"""SMPL joint layout, anatomical joint limits and the rest-pose correction for body models.

Motions in `synth.motions` are authored as intrinsic XYZ Euler angles (radians) per joint,
relative to the SMPL T-pose in SMPL axes (x = body left, y = up, z = facing). For every joint:
x is the sagittal angle (flexion / extension), y the rotation about the vertical (twist for legs
and spine), z the frontal-plane angle (abduction, side bend). Angles are written for the left
side; the right side is the mirror image (y and z negated), see `mirror_angles`.

Body models whose rest pose is not a T-pose (Anny rests in an A-pose) are handled by
`rest_corrections`: a per-joint rotation C_j that turns the model's rest bone into the T-pose
bone, so that a local rotation authored against the T-pose becomes L_j = C_parent^T A_j C_j.
"""

from __future__ import annotations

import numpy as np

from gst.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS

# The SMPL layout is gst.body's; synth names it in its own terms.
JOINT_NAMES: tuple[str, ...] = SMPL_JOINT_NAMES
NUM_JOINTS = len(JOINT_NAMES)
PARENTS: tuple[int, ...] = SMPL_PARENTS
J = {name: i for i, name in enumerate(JOINT_NAMES)}

# Index of each joint's mirror image (left <-> right, central joints map to themselves).
MIRROR: tuple[int, ...] = tuple(
    J[n.replace("left_", "right_")]
    if n.startswith("left_")
    else J[n.replace("right_", "left_")]
    if n.startswith("right_")
    else i
    for i, n in enumerate(JOINT_NAMES)
)

# Primary child of each joint (the bone it rotates), -1 for leaves.
PRIMARY_CHILD: tuple[int, ...] = tuple(
    {0: J["spine1"], 9: J["neck"]}.get(i, next((c for c, p in enumerate(PARENTS) if p == i), -1))
    for i in range(NUM_JOINTS)
)

# T-pose direction (SMPL axes) of the bones whose rest direction differs between body models.
# Only long limb bones are corrected; ankles, feet, wrists and hands inherit their parent's
# correction so hands and feet keep their rest orientation relative to the limb.
_TPOSE_BONE_DIRECTION = {
    "left_hip": (0.0, -1.0, 0.0),
    "right_hip": (0.0, -1.0, 0.0),
    "left_knee": (0.0, -1.0, 0.0),
    "right_knee": (0.0, -1.0, 0.0),
    "left_shoulder": (1.0, 0.0, 0.0),
    "right_shoulder": (-1.0, 0.0, 0.0),
    "left_elbow": (1.0, 0.0, 0.0),
    "right_elbow": (-1.0, 0.0, 0.0),
}
_INHERIT = (
    "left_ankle",
    "right_ankle",
    "left_foot",
    "right_foot",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)

# Joint limits in degrees for the left side, (lo, hi) per Euler axis x, y, z. Index 0 is the
# root tilt relative to upright (heading is separate). Sign conventions (left side):
#   hip x < 0 flexes the thigh forward; knee x > 0 flexes; ankle x > 0 points the toes down;
#   spine/neck x > 0 bends forward; shoulder z = -90 hangs the arm down, z > 0 raises it;
#   shoulder x < 0 swings the (hanging) arm forward; elbow y < 0 flexes.
_LIMITS_LEFT_DEG = {
    "pelvis": ((-40, 85), (-45, 45), (-30, 30)),
    "left_hip": ((-125, 40), (-40, 40), (-25, 60)),
    "spine1": ((-20, 45), (-25, 25), (-20, 20)),
    "left_knee": ((0, 150), (-5, 5), (-5, 5)),
    "spine2": ((-15, 35), (-25, 25), (-20, 20)),
    "left_ankle": ((-30, 50), (-20, 20), (-20, 20)),
    "spine3": ((-15, 30), (-25, 25), (-20, 20)),
    "left_foot": ((-40, 30), (-10, 10), (-10, 10)),
    "neck": ((-35, 45), (-50, 50), (-30, 30)),
    "left_collar": ((-20, 20), (-25, 25), (-15, 30)),
    "head": ((-30, 35), (-35, 35), (-25, 25)),
    "left_shoulder": ((-170, 70), (-85, 85), (-100, 95)),
    "left_elbow": ((-10, 10), (-150, 0), (-80, 80)),
    "left_wrist": ((-40, 40), (-60, 60), (-70, 70)),
    "left_hand": ((-20, 20), (-20, 20), (-30, 30)),
}


def _limits_table() -> np.ndarray:
    """(24, 3, 2) joint limits in radians for every joint (right side mirrored)."""
    table = np.zeros((NUM_JOINTS, 3, 2))
    for name, axes in _LIMITS_LEFT_DEG.items():
        table[J[name]] = np.deg2rad(np.asarray(axes, dtype=np.float64))
    for i, name in enumerate(JOINT_NAMES):
        if name.startswith("right_"):
            left = table[MIRROR[i]]
            table[i, 0] = left[0]
            table[i, 1] = -left[1, ::-1]
            table[i, 2] = -left[2, ::-1]
    return table


JOINT_LIMITS: np.ndarray = _limits_table()


def mirror_angles(angles: np.ndarray) -> np.ndarray:
    """Mirror (..., 24, 3) Euler angles across the sagittal plane: swap left and right joints
    and negate the y and z angles."""
    out = np.asarray(angles)[..., list(MIRROR), :].copy()
    out[..., 1:] *= -1.0
    return out


def soft_clip(
    x: np.ndarray, lo: np.ndarray, hi: np.ndarray, knee: float = np.deg2rad(8)
) -> np.ndarray:
    """Clip to [lo, hi] with smooth (C1) shoulders of width `knee`, so clipped motion stays
    smooth in time. Values well inside the range are unchanged."""
    x = np.asarray(x, dtype=np.float64)
    lo = np.broadcast_to(lo, x.shape)
    hi = np.broadcast_to(hi, x.shape)
    k = np.minimum(knee, 0.25 * (hi - lo))
    k = np.maximum(k, 1e-9)
    out = x.copy()
    # Above hi - k: approach hi asymptotically with matching slope at the joint.
    up = x > hi - k
    d = (x[up] - (hi[up] - k[up])) / k[up]
    out[up] = hi[up] - k[up] + k[up] * np.tanh(d)
    down = x < lo + k
    d = ((lo[down] + k[down]) - x[down]) / k[down]
    out[down] = lo[down] + k[down] - k[down] * np.tanh(d)
    return out


def clip_to_limits(angles: np.ndarray) -> np.ndarray:
    """Softly clip (..., 24, 3) authored Euler angles to `JOINT_LIMITS`."""
    return soft_clip(angles, JOINT_LIMITS[..., 0], JOINT_LIMITS[..., 1])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation matrix taking direction `a` to direction `b` (3-vectors)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite directions: rotate by pi about any axis orthogonal to a.
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)


def rest_corrections(rest_joints: np.ndarray) -> np.ndarray:
    """Per-joint rotations (24, 3, 3) that turn a model's rest pose into the SMPL T-pose.

    `rest_joints` is (24, 3) in SMPL axes at zero pose. For a model already in a T-pose the
    result is (close to) the identity everywhere.
    """
    rest_joints = np.asarray(rest_joints, dtype=np.float64)
    if rest_joints.shape != (NUM_JOINTS, 3):
        raise ValueError(f"rest joints have shape {rest_joints.shape}, expected ({NUM_JOINTS}, 3)")
    C = np.tile(np.eye(3), (NUM_JOINTS, 1, 1))
    for name, target in _TPOSE_BONE_DIRECTION.items():
        j = J[name]
        bone = rest_joints[PRIMARY_CHILD[j]] - rest_joints[j]
        C[j] = rotation_between(bone, target)
    for name in _INHERIT:  # parents come earlier in this tuple than their children
        j = J[name]
        C[j] = C[PARENTS[j]]
    return C


def local_rotations(authored: np.ndarray, corrections: np.ndarray) -> np.ndarray:
    """Model-space local rotations L_j = C_parent^T A_j C_j for (..., 24, 3, 3) authored
    rotations A. Joint 0 (root) is returned unchanged; the caller composes it with the heading."""
    authored = np.asarray(authored, dtype=np.float64)
    out = authored.copy()
    for j in range(1, NUM_JOINTS):
        p = PARENTS[j]
        out[..., j, :, :] = corrections[p].T @ authored[..., j, :, :] @ corrections[j]
    return out
