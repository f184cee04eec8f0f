"""Rotation representations used by the body model and the network.

Conventions: rotation matrices act on column vectors (x' = R x); axis-angle vectors are the unit
axis times the angle in radians (right-hand rule). The 6D representation follows HMR2 / Zhou et
al. 2019: the six numbers are the first two COLUMNS of the rotation matrix, ``x[..., :3]`` being
column 0 and ``x[..., 3:]`` column 1; ``rot6d_to_matrix`` orthonormalises them by Gram-Schmidt
and takes column 2 as their cross product.

Axis-angle conversions are kornia's (stable and differentiable at the identity, exact branch
selection near a half turn); the 6D map is written here because kornia has none.
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

__all__ = ["rot6d_to_matrix", "matrix_to_rot6d", "axis_angle_to_matrix", "matrix_to_axis_angle"]

# Floor on the norms in Gram-Schmidt, so that a degenerate 6D input gives a finite (if arbitrary)
# result and a finite gradient instead of NaN.
_GS_EPS = 1e-12


def _check_last_dims(x: torch.Tensor, dims: tuple[int, ...], name: str, fn: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{fn}: {name} must be a torch.Tensor, got {type(x).__name__}")
    if tuple(x.shape[x.dim() - len(dims) :]) != dims or x.dim() < len(dims):
        want = "(..., " + ", ".join(map(str, dims)) + ")"
        raise ValueError(f"{fn}: {name} must have shape {want}, got {tuple(x.shape)}")


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """6D rotation (..., 6) -> rotation matrix (..., 3, 3), HMR2 convention.

    ``x[..., :3]`` and ``x[..., 3:]`` are the (unnormalised) first and second COLUMNS of the
    matrix. Column 0 is the normalised first vector, column 1 the second vector minus its
    projection on column 0, normalised, and column 2 their cross product, so the result is
    always a proper rotation (det +1). A degenerate input (a zero or parallel pair) returns a
    finite matrix rather than NaN; it is not a rotation, so keep the network away from it.
    """
    _check_last_dims(x, (6,), "x", "rot6d_to_matrix")
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(_GS_EPS)
    a2_perp = a2 - (b1 * a2).sum(dim=-1, keepdim=True) * b1
    b2 = a2_perp / a2_perp.norm(dim=-1, keepdim=True).clamp_min(_GS_EPS)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) -> 6D (..., 6): its first two columns, column 0 first.

    ``rot6d_to_matrix(matrix_to_rot6d(R)) == R`` for any rotation R (up to rounding).
    """
    _check_last_dims(R, (3, 3), "R", "matrix_to_rot6d")
    return torch.cat((R[..., :, 0], R[..., :, 1]), dim=-1)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3), radians -> rotation matrix (..., 3, 3) (Rodrigues, via kornia).

    Uses a Taylor expansion below 1e-3 rad, so it is exact and differentiable at zero.
    """
    _check_last_dims(axis_angle, (3,), "axis_angle", "axis_angle_to_matrix")
    # kornia squares the angle, which overflows float32 above ~1.8e19 rad (NaN out and in the
    # gradient). Rotations are 2 pi periodic: wrap larger angles first, with the norm taken in
    # float64 so that it cannot overflow. Angles up to 2 pi pass through unchanged.
    theta = torch.linalg.vector_norm(axis_angle.double(), dim=-1, keepdim=True)
    big = theta > 2 * math.pi
    shrink = torch.remainder(theta, 2 * math.pi) / torch.where(big, theta, torch.ones_like(theta))
    axis_angle = axis_angle * torch.where(big, shrink, torch.ones_like(theta)).to(axis_angle.dtype)
    return axis_angle_to_rotation_matrix(axis_angle)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) -> axis-angle (..., 3), angle in [0, pi] (via kornia).

    Goes through a quaternion with Shepperd's branch selection, so it stays accurate near the
    identity and near a half turn (where the axis sign is arbitrary: both signs are the same
    rotation).
    """
    _check_last_dims(R, (3, 3), "R", "matrix_to_axis_angle")
    return rotation_matrix_to_axis_angle(R)
