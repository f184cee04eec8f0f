"""World convention of synthetic scenes and the rotations that place SMPL-axis bodies in it.

World: metres, Z up, the floor is the plane z = 0. Bodies are modelled in SMPL axes
(x = body left, y = up, z = facing) and placed with the fixed rotation
(x, y, z)_world = (x, -z, y)_smpl, then a heading about world Z and a translation.
A body with heading theta faces the world direction (cos theta, sin theta, 0).
"""

from __future__ import annotations

import numpy as np

WORLD_UP = (0.0, 0.0, 1.0)

# world = SMPL_TO_WORLD @ smpl: SMPL up (+y) -> world +Z, SMPL facing (+z) -> world -Y.
SMPL_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

WORLD_CONVENTION = {
    "units": "m",
    "up": list(WORLD_UP),
    "floor": "z = 0",
    "smpl_to_world": SMPL_TO_WORLD.tolist(),
    "heading": "a body with heading theta (radians) faces (cos theta, sin theta, 0)",
    "extrinsics": "world to camera, X_cam = R X_world + t, OpenCV camera axes",
}


def rot_z(angle: np.ndarray | float) -> np.ndarray:
    """Rotation(s) about world Z; returns (..., 3, 3)."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def heading_rotation(heading: np.ndarray | float) -> np.ndarray:
    """World rotation (..., 3, 3) taking an SMPL-axis body to world axes facing `heading`.

    The SMPL body faces world -Y after SMPL_TO_WORLD, which is heading -pi/2, so the yaw is
    heading + pi/2.
    """
    return rot_z(np.asarray(heading, dtype=np.float64) + np.pi / 2) @ SMPL_TO_WORLD


def facing_direction(heading: np.ndarray | float) -> np.ndarray:
    """Unit world direction (..., 3) a body with `heading` faces."""
    h = np.asarray(heading, dtype=np.float64)
    return np.stack([np.cos(h), np.sin(h), np.zeros_like(h)], -1)
