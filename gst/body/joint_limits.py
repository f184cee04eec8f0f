"""Rough anatomical joint limits for the SMPL skeleton, and a sampler of random poses within them.

Limits are per joint and per axis, in degrees, for the local rotation R = Rx(a) Ry(b) Rz(c)
(angles about the SMPL model axes: X body-left, Y up, Z forward). Signs, for the left side
(the right side mirrors Y and Z): knee flexion is +X, hip flexion (thigh forward) is -X, hip
abduction is +Z, arm raise is +Z, elbow flexion is -Y, spine and neck flexion are +X.

They are meant for plausible random poses (tests, synthetic people), not for biomechanics; they
are relative to each model's own rest pose (SMPL: T-pose; the Anny default: arms lowered).
"""

from __future__ import annotations

import numpy as np
import torch

from gst.body.skeleton import SMPL_JOINT_NAMES

__all__ = ["JOINT_LIMITS_DEG", "sample_body_pose", "euler_xyz_to_matrix"]

_Range = tuple[float, float]

_LEFT: dict[str, tuple[_Range, _Range, _Range]] = {
    "hip": ((-110.0, 25.0), (-35.0, 35.0), (-25.0, 45.0)),
    "knee": ((0.0, 130.0), (-10.0, 10.0), (-5.0, 5.0)),
    "ankle": ((-25.0, 40.0), (-15.0, 15.0), (-20.0, 20.0)),
    "foot": ((-25.0, 25.0), (-5.0, 5.0), (-5.0, 5.0)),
    "collar": ((-10.0, 10.0), (-15.0, 15.0), (-10.0, 20.0)),
    "shoulder": ((-60.0, 60.0), (-80.0, 40.0), (-40.0, 80.0)),
    "elbow": ((-40.0, 40.0), (-130.0, 0.0), (-5.0, 5.0)),
    "wrist": ((-40.0, 40.0), (-50.0, 50.0), (-25.0, 25.0)),
    "hand": ((-15.0, 15.0), (-20.0, 20.0), (-15.0, 15.0)),
}
_CENTRAL: dict[str, tuple[_Range, _Range, _Range]] = {
    "spine1": ((-15.0, 35.0), (-25.0, 25.0), (-15.0, 15.0)),
    "spine2": ((-10.0, 25.0), (-20.0, 20.0), (-10.0, 10.0)),
    "spine3": ((-10.0, 20.0), (-15.0, 15.0), (-10.0, 10.0)),
    "neck": ((-25.0, 35.0), (-40.0, 40.0), (-25.0, 25.0)),
    "head": ((-25.0, 25.0), (-30.0, 30.0), (-20.0, 20.0)),
}


def _limits() -> dict[str, tuple[_Range, _Range, _Range]]:
    out: dict[str, tuple[_Range, _Range, _Range]] = dict(_CENTRAL)
    for joint, (x, (y0, y1), (z0, z1)) in _LEFT.items():
        out[f"left_{joint}"] = (x, (y0, y1), (z0, z1))
        out[f"right_{joint}"] = (x, (-y1, -y0), (-z1, -z0))
    return out


JOINT_LIMITS_DEG: dict[str, tuple[_Range, _Range, _Range]] = _limits()


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """(..., 3) angles (a, b, c) in radians -> Rx(a) @ Ry(b) @ Rz(c), (..., 3, 3)."""
    a, b, c = angles.unbind(-1)
    one, zero = torch.ones_like(a), torch.zeros_like(a)

    def mat(rows):
        return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)

    rx = mat([[one, zero, zero], [zero, a.cos(), -a.sin()], [zero, a.sin(), a.cos()]])
    ry = mat([[b.cos(), zero, b.sin()], [zero, one, zero], [-b.sin(), zero, b.cos()]])
    rz = mat([[c.cos(), -c.sin(), zero], [c.sin(), c.cos(), zero], [zero, zero, one]])
    return rx @ ry @ rz


def sample_body_pose(
    n: int,
    generator: torch.Generator | None = None,
    scale: float = 1.0,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """(n, 23, 3, 3) local rotations of SMPL joints 1..23, each angle uniform within its limits
    (limits scaled about zero by ``scale``, which must lie in [0, 1])."""
    if not 0.0 <= scale <= 1.0:
        raise ValueError(f"scale must lie in [0, 1], got {scale}")
    names = SMPL_JOINT_NAMES[1:]
    lo = torch.tensor(
        [[r[0] for r in JOINT_LIMITS_DEG[name]] for name in names], dtype=torch.float64
    )
    hi = torch.tensor(
        [[r[1] for r in JOINT_LIMITS_DEG[name]] for name in names], dtype=torch.float64
    )
    u = torch.rand((n, len(names), 3), generator=generator, dtype=torch.float64)
    angles = np.deg2rad(1.0) * scale * (lo + u * (hi - lo))
    return euler_xyz_to_matrix(angles).to(dtype)
