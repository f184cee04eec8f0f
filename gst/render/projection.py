"""EWA projection of 3D Gaussians into pinhole cameras (differentiable, pure torch).

Follows the 3DGS / gsplat "classic" projection: world-to-camera transform, the affine
(Jacobian) approximation of the perspective map at the Gaussian's centre, with the centre's
x/z and y/z clamped to 1.3 times the field of view so that off-screen Gaussians do not blow up,
and a 0.3 px^2 low-pass added to the 2D covariance. Pixel centres are integers (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gst.render.conventions import LOWPASS_EPS2D, QUAT_EPS, SCALE_MAX


@dataclass
class ProjectedGaussians:
    """Per (scene, camera, Gaussian) screen-space quantities; leading dims (S, C, N)."""

    means2d: Tensor  # (S, C, N, 2) pixel coordinates, integer pixel centres
    conics: Tensor  # (S, C, N, 3) inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: Tensor  # (S, C, N) camera-space z of the centre
    radii: Tensor  # (S, C, N, 2) sqrt of the 2D covariance diagonal (px), for bounding boxes
    valid: Tensor  # (S, C, N) bool: centre at or beyond the near plane


def quats_to_rotmats(quats: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) from wxyz quaternions (..., 4), normalised per Gaussian.

    Unnormalised quaternions are normalised; a (near-)zero quaternion gives the identity, with
    finite gradients.
    """
    # Divide by the largest component (when above 1) first: the squares inside the norm overflow
    # float32 above ~1.8e19 and turned such quaternions into the identity. q / |q| does not
    # depend on that factor, so detaching it leaves the gradient exact.
    big = quats.detach().abs().amax(dim=-1, keepdim=True).clamp_min(1.0)
    quats = quats / big
    norm = torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    # Below QUAT_EPS, (0, 0, 0, 0), which the formula below turns into the identity (as the gsplat
    # backend and the PLY writer read it): dividing by the clamped norm left such a quaternion
    # short of unit length, not a rotation (|q| = 5e-13 scaled two axes by 0.5).
    q = torch.where(norm > QUAT_EPS, quats / norm.clamp_min(QUAT_EPS), torch.zeros_like(quats))
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rot.reshape(*quats.shape[:-1], 3, 3)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near: float,
) -> ProjectedGaussians:
    """Project Gaussians (S, N, ...) into cameras (S, C, ...); see the module docstring.

    Gaussians whose centre is nearer than `near` are marked invalid; their outputs are finite
    placeholders (computed at depth 1) so that masked-out values never produce NaN gradients.
    """
    rot_w2c = viewmats[..., :3, :3]  # (S, C, 3, 3)
    t_w2c = viewmats[..., :3, 3]  # (S, C, 3)
    means_c = torch.einsum("scij,snj->scni", rot_w2c, means) + t_w2c[:, :, None, :]
    x, y, z = means_c.unbind(-1)  # (S, C, N)
    valid = z >= near
    z_safe = torch.where(valid, z, torch.ones_like(z))

    fx = Ks[..., 0, 0][..., None]  # (S, C, 1)
    fy = Ks[..., 1, 1][..., None]
    cx = Ks[..., 0, 2][..., None]
    cy = Ks[..., 1, 2][..., None]

    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    # Clamp the direction used by the Jacobian to 1.3x the field of view, measured from the
    # image edges at -0.5 and width - 0.5 (integer pixel centres): the same limits gsplat uses.
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - 0.5 - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = (cx + 0.5) / fx + 0.3 * tan_fovx
    lim_y_pos = (height - 0.5 - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = (cy + 0.5) / fy + 0.3 * tan_fovy
    tx = torch.maximum(torch.minimum(x / z_safe, lim_x_pos), -lim_x_neg)
    ty = torch.maximum(torch.minimum(y / z_safe, lim_y_pos), -lim_y_neg)

    # J (2x3) of the perspective map, times the world-to-camera rotation: rows (S, C, N, 3).
    zero = torch.zeros_like(z_safe)
    jac = torch.stack(
        [
            torch.stack([fx / z_safe, zero, -fx * tx / z_safe], dim=-1),
            torch.stack([zero, fy / z_safe, -fy * ty / z_safe], dim=-1),
        ],
        dim=-2,
    )  # (S, C, N, 2, 3)
    jw = jac @ rot_w2c[:, :, None]  # (S, C, N, 2, 3)

    # Sigma_2d = T T^T with T = J W R_q diag(s): no 3x3 covariance needed.
    scales = scales.clamp(max=SCALE_MAX)
    m = quats_to_rotmats(quats) * scales[..., None, :]  # (S, N, 3, 3) = R_q diag(s)
    t = jw @ m[:, None]  # (S, C, N, 2, 3)

    # Rescale T by a detached per-Gaussian factor k so huge covariances cannot overflow; all
    # quantities below are then in units of k^2 and rescaled at the end.
    k = t.detach().abs().amax(dim=(-1, -2)).clamp_min(1.0)  # (S, C, N)
    tn = t / k[..., None, None]
    eps = LOWPASS_EPS2D / (k * k)
    r1, r2 = tn[..., 0, :], tn[..., 1, :]
    a0 = (r1 * r1).sum(-1)
    b0 = (r1 * r2).sum(-1)
    c0 = (r2 * r2).sum(-1)
    # det(T T^T + eps I) = |r1 x r2|^2 + eps (a0 + c0) + eps^2: a sum of non-negative terms,
    # so it never cancels to zero or below, however elongated the Gaussian.
    cross = torch.linalg.cross(r1, r2, dim=-1)
    det = (cross * cross).sum(-1) + eps * (a0 + c0) + eps * eps
    a = a0 + eps
    c = c0 + eps
    inv = 1.0 / (det * (k * k))
    conics = torch.stack([c * inv, -b0 * inv, a * inv], dim=-1)
    radii = torch.stack([torch.sqrt(a) * k, torch.sqrt(c) * k], dim=-1)
    return ProjectedGaussians(
        means2d=means2d, conics=conics, depths=z, radii=radii.detach(), valid=valid
    )
