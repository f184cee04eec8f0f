"""The body fit's energy, per person-frame, and its Gauss-Newton (IRLS) linearisation.

    E = data + w_smooth * smoothness + w_pose * |theta|^2 + w_limits * (joint-limit excess)^2

- data, 2D (`Views`): sum over cameras and landmarks of confidence * log(1 + (r/sigma)^2) with r
  the full-image pixel distance between the projected marker and the landmark and sigma the
  noise level (so noisier evidence leans more on the priors); the Cauchy kernel makes wrong
  detections (the other person, a left/right swap) saturate;
- data, 3D (`Points`, the start): the same kernel on the distance to triangulated landmarks;
- silhouettes (`Coverage`, optional): the same kernel on how far (full-image px) each marker
  projects outside the people of every view that has a crop (gst.fuse.silhouettes), whatever
  its landmarks say: a limb that half the views read somewhere else still has to lie on
  someone in all of them;
- floor (`Floor`, optional): the squared depth of each marker below its lowest possible height
  above the floor plane (a heel cannot sink into the ground; one-sided, zero above it);
- smoothness: Cauchy of each marker's second difference over consecutive frames, in units of
  `smooth_scale_m` at 30 fps (scaled by (30 / fps)^2, so a weight means the same at any rate);
- pose prior (rest pose is the mode) and squared excess of the local rotations' X-Y-Z Euler
  angles over gst.body.joint_limits.

The linearisation is IRLS: Cauchy weights are frozen at the current residuals, so the normal
equations of the weighted least squares are those of the robust energy at that point. Every data
and smoothness term acts on markers, so it is summed first into a 3x3 information matrix and a
gradient per marker (`Hm`, `gm`), then mapped through the marker Jacobian once:
H = sum_m dX_m^T Hm dX_m: the cost is linear in cameras and in person-frames. Smoothness couples
neighbouring frames; each frame's block holds its own exact gradient and the diagonal block of the
Hessian, with the neighbours held (block Jacobi), and the solver's accept test uses the full
energy, so the coupling is never trusted further than it helps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gst.body.kinematics import N_POSE_PARAMS, left_jacobian, skew

__all__ = [
    "Views", "Points", "Coverage", "Floor", "Neighbours", "Weights", "euler_xyz", "data_cost",
    "linearise",
]  # fmt: skip


@dataclass
class Views:
    """2D evidence of B person-frames on C cameras, M landmarks."""

    K: torch.Tensor  # (B, C, 3, 3) the crop's intrinsics (undistorted)
    Rt: torch.Tensor  # (B, C, 3, 4) world -> camera
    uv: torch.Tensor  # (B, C, M, 2) crop pixels (0 where unobserved)
    weight: torch.Tensor  # (B, C, M) confidence, 0 where unobserved or dropped
    scale: torch.Tensor  # (B, C) crop pixel -> full-image pixel
    sigma: torch.Tensor  # (B,) Cauchy scale, full-image px

    def project(self, X: torch.Tensor):
        """Crop pixels (B, C, M, 2), camera points and depths of markers X (B, M, 3)."""
        cam = torch.einsum("bcij,bmj->bcmi", self.Rt[..., :3], X) + self.Rt[:, :, None, :, 3]
        z = cam[..., 2:].clamp_min(1e-3)
        q = torch.einsum("bcij,bcmj->bcmi", self.K, cam)
        return q[..., :2] / z, z

    def residuals(self, X: torch.Tensor) -> torch.Tensor:
        """(B, C, M) full-image pixel distances."""
        uv, _ = self.project(X)
        return (uv - self.uv).norm(dim=-1) * self.scale[..., None]

    def jacobian(self, uv: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """d uv / d X (B, C, M, 2, 3) in full-image pixels per metre, at projections uv (crop
        pixels) of depth z: (K[:2] - uv e3^T) / z @ R, times the crop's pixel scale."""
        e3 = torch.tensor([0.0, 0.0, 1.0], dtype=uv.dtype)
        Pc = (self.K[:, :, None, :2, :] - uv[..., :, None] * e3) / z[..., None]
        return Pc @ self.Rt[:, :, None, :, :3] * self.scale[..., None, None, None]


@dataclass
class Coverage:
    """Silhouette evidence of B person-frames on the C cameras of `views` (whose K, Rt and scale
    it uses): per view a distance field over the crop, crop pixels from each cell to the nearest
    cell covered by a person, and its gradient (gst.fuse.silhouettes)."""

    views: Views
    fields: torch.Tensor  # (B * C, 3, s, s): distance (crop px), d/du, d/dv
    weight: torch.Tensor  # (B, C) 0 where the view has no crop
    sigma: torch.Tensor  # (B,) Cauchy scale, full-image px
    crop_size: int  # crop pixels across a crop (the fields span it)

    def sample(self, X: torch.Tensor):
        """For markers X (B, M, 3): distances (B, C, M) in full-image px, their gradients
        (B, C, M, 2) per crop pixel of projection, the projections (crop px) and depths."""
        uv, z = self.views.project(X)
        B, C, M = uv.shape[:3]
        # the fields span the crop's pixels, whose centres are integers: its edges lie at -0.5
        # and crop_size - 0.5 (grid_sample's -1 and 1 with align_corners=False)
        grid = ((uv + 0.5) / self.crop_size * 2 - 1).reshape(B * C, 1, M, 2)
        grid = grid.to(self.fields.dtype)
        at = (
            torch.nn.functional.grid_sample(
                self.fields, grid, mode="bilinear", padding_mode="border", align_corners=False
            )[:, :, 0]
            .reshape(B, C, 3, M)
            .to(X.dtype)
        )
        return at[:, :, 0] * self.views.scale[..., None], at[:, :, 1:].transpose(-1, -2), uv, z


@dataclass
class Points:
    """3D evidence: triangulated landmarks (B, M, 3) with weights (B, M)."""

    X: torch.Tensor
    weight: torch.Tensor
    sigma_m: float


@dataclass
class Floor:
    """The ground: no marker m may lie lower than `height + clearance[m]` along `up` (world);
    energy `weight` per m^2 of the depth below that. `height` is one number, or one per row
    (B, 1) with -inf for the rows of people who stand on other ground (`gst.fuse.floor`)."""

    up: torch.Tensor  # (3,) unit
    height: float | torch.Tensor  # metres along `up`; or (B, 1), -inf: no floor for that row
    clearance: torch.Tensor  # (M,) metres: each marker's lowest height above the floor
    weight: float

    def depth(self, X: torch.Tensor) -> torch.Tensor:
        """(B, M) metres below the allowed height (0 where above it)."""
        height = self.height.to(X) if isinstance(self.height, torch.Tensor) else self.height
        return (height + self.clearance - X @ self.up.to(X)).clamp_min(0)


@dataclass
class Neighbours:
    """Consecutive frames of the same person inside the batch (indices clamped to valid rows)."""

    prev: torch.Tensor  # (B,) index of frame t-1 (self where none)
    next: torch.Tensor  # (B,)
    has_prev: torch.Tensor  # (B,) bool
    has_next: torch.Tensor  # (B,) bool

    @property
    def centred(self) -> torch.Tensor:
        """(B,) bool: a second difference is centred on this frame."""
        return self.has_prev & self.has_next


@dataclass(frozen=True)
class Weights:
    pose: float
    limits: float
    smooth: float
    accel_scale: float  # 1 / (smoothing scale in metres), times (fps / 30)^2
    limits_lo: torch.Tensor  # (23, 3) radians
    limits_hi: torch.Tensor


def euler_xyz(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3) angles (a, b, c) with R = Rx(a) Ry(b) Rz(c) (joint_limits' order)."""
    b = torch.asin(R[..., 0, 2].clamp(-1 + 1e-6, 1 - 1e-6))
    a = torch.atan2(-R[..., 1, 2], R[..., 2, 2])
    c = torch.atan2(-R[..., 0, 1], R[..., 0, 0])
    return torch.stack([a, b, c], -1)


def _euler_jacobian(local: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """d euler_xyz(exp(theta)) / d theta, (..., 3 angles, 3)."""
    axes = left_jacobian(theta).transpose(-1, -2)  # row k: axis turned by d theta_k
    dR = skew(axes) @ local[..., None, :, :]  # (..., 3 k, 3, 3)
    R = local[..., None, :, :]
    db = dR[..., 0, 2] / (1 - R[..., 0, 2] ** 2).clamp_min(1e-12).sqrt()
    da = (R[..., 1, 2] * dR[..., 2, 2] - dR[..., 1, 2] * R[..., 2, 2]) / (
        R[..., 1, 2] ** 2 + R[..., 2, 2] ** 2
    ).clamp_min(1e-12)
    dc = (R[..., 0, 1] * dR[..., 0, 0] - dR[..., 0, 1] * R[..., 0, 0]) / (
        R[..., 0, 1] ** 2 + R[..., 0, 0] ** 2
    ).clamp_min(1e-12)
    return torch.stack([da, db, dc], -2)


def _limit_excess(local: torch.Tensor, w: Weights) -> tuple[torch.Tensor, torch.Tensor]:
    ang = euler_xyz(local)
    lo, hi = w.limits_lo.to(ang), w.limits_hi.to(ang)
    return torch.where(ang < lo, ang - lo, torch.where(ang > hi, ang - hi, 0 * ang)), ang


def _second_difference(X: torch.Tensor, nb: Neighbours, w: Weights) -> torch.Tensor:
    a = (X[nb.prev] - 2 * X + X[nb.next]) * w.accel_scale
    return torch.where(nb.centred[:, None, None], a, torch.zeros_like(a))


def data_cost(X: torch.Tensor, evidence: Views | Points | Coverage | Floor) -> torch.Tensor:
    """(B,) robust data term."""
    if isinstance(evidence, Floor):
        return evidence.weight * (evidence.depth(X) ** 2).sum(-1)
    if isinstance(evidence, Points):
        r2 = ((X - evidence.X) ** 2).sum(-1) / evidence.sigma_m**2
        return (evidence.weight * torch.log1p(r2)).sum(-1)
    if isinstance(evidence, Coverage):
        r2 = evidence.sample(X)[0] ** 2 / evidence.sigma[:, None, None] ** 2
        return (evidence.weight[..., None] * torch.log1p(r2)).sum((1, 2))
    r2 = evidence.residuals(X) ** 2 / evidence.sigma[:, None, None] ** 2
    return (evidence.weight * torch.log1p(r2)).sum((1, 2))


def cost(X, theta, local, evidence, nb: Neighbours, w: Weights) -> torch.Tensor:
    """(B,) energy per person-frame (the smoothness term counted at its centre frame).
    `evidence`: Views, Points or a sequence of them (their data terms add up)."""
    exc, _ = _limit_excess(local, w)
    e = w.pose * (theta**2).sum((1, 2)) + w.limits * (exc**2).sum((1, 2))
    for ev in _as_list(evidence):
        e = e + data_cost(X, ev)
    if w.smooth > 0:
        a = _second_difference(X, nb, w)
        e = e + w.smooth * torch.log1p((a**2).sum(-1)).sum(-1)
    return e


def _as_list(evidence) -> list:
    return list(evidence) if isinstance(evidence, list | tuple) else [evidence]


def _marker_information(X, ev: Views | Points | Coverage | Floor):
    """Per marker information matrix (B, M, 3, 3) and gradient (B, M, 3) of a data term."""
    eye = torch.eye(3, dtype=X.dtype)
    if isinstance(ev, Floor):
        d = ev.depth(X)  # E = w d^2 with d(X) = const - up.X where positive
        up = ev.up.to(X)
        w = ev.weight * (d > 0).to(X.dtype)
        return w[..., None, None] * torch.outer(up, up), -(ev.weight * d)[..., None] * up
    if isinstance(ev, Points):
        d = X - ev.X
        s2 = ev.sigma_m**2
        wm = ev.weight / (1 + (d**2).sum(-1) / s2) / s2  # IRLS weights (B, M)
        return wm[..., None, None] * eye, wm[..., None] * d
    if isinstance(ev, Coverage):
        r, grad, uv, z = ev.sample(X)  # (B, C, M) full px, (B, C, M, 2)
        s2 = ev.sigma[:, None, None] ** 2
        wv = ev.weight[..., None] / (1 + r**2 / s2) / s2
        J = (grad[..., None, :] @ ev.views.jacobian(uv, z))[..., 0, :]  # (B, C, M, 3)
        Jw = J * wv[..., None]
        return torch.einsum("bcmi,bcmj->bmij", Jw, J), torch.einsum("bcmi,bcm->bmi", Jw, r)
    uv, z = ev.project(X)
    res = (uv - ev.uv) * ev.scale[..., None, None]  # (B, C, M, 2) full px
    s2 = ev.sigma[:, None, None] ** 2
    wv = ev.weight / (1 + (res**2).sum(-1) / s2) / s2  # IRLS weights (B, C, M)
    P = ev.jacobian(uv, z)  # (B, C, M, 2, 3)
    Pw = P * wv[..., None, None]
    return torch.einsum("bcmki,bcmkj->bmij", Pw, P), torch.einsum("bcmki,bcmk->bmi", Pw, res)


def linearise(X, dX, theta, local, evidence, nb: Neighbours, w: Weights, turn=None):
    """Normal equations H (B, P, P), g (B, P) (E ~ E0 + 2 g.dp + dp.H.dp) at the current state.

    `turn` (B, M, 3, 3): when the person's marker offsets are unknowns too, the rotation that
    turns each marker's offset (d X_m / d offset_m); their 3 M columns come last."""
    B, M = X.shape[:2]
    eye = torch.eye(3, dtype=X.dtype)
    Hm = X.new_zeros(B, M, 3, 3)
    gm = X.new_zeros(B, M, 3)
    for ev in _as_list(evidence):
        h, g_ = _marker_information(X, ev)
        Hm, gm = Hm + h, gm + g_
    if w.smooth > 0:
        a = _second_difference(X, nb, w)  # (B, M, 3), zero where not centred
        ws = w.smooth / (1 + (a**2).sum(-1))  # IRLS weights (B, M)
        wa = ws[..., None] * a
        c = nb.centred
        # frame t appears in the differences centred at t-1 (+1), t (-2) and t+1 (+1)
        wp = torch.where((nb.has_prev & c[nb.prev])[:, None], ws[nb.prev], 0 * ws)
        wn = torch.where((nb.has_next & c[nb.next])[:, None], ws[nb.next], 0 * ws)
        gm = gm + w.accel_scale * (
            wa[nb.prev] * (wp > 0)[..., None] - 2 * wa + wa[nb.next] * (wn > 0)[..., None]
        )
        Hm = Hm + (w.accel_scale**2 * (wp + 4 * ws * c[:, None] + wn))[..., None, None] * eye
    J = dX.reshape(B, M * 3, -1)
    HJ = Hm @ dX  # (B, M, 3, P)
    H = J.transpose(1, 2) @ HJ.reshape(B, M * 3, -1)
    g = (J.transpose(1, 2) @ gm.reshape(B, M * 3, 1))[..., 0]
    # pose prior and joint limits act on theta (columns 6..75), one 3x3 block per joint
    idx = torch.arange(6, N_POSE_PARAMS)
    H[:, idx, idx] += w.pose
    g[:, 6:N_POSE_PARAMS] += w.pose * theta.reshape(B, 69)
    exc, _ = _limit_excess(local, w)
    D = _euler_jacobian(local, theta) * (exc != 0).to(X.dtype)[..., None]  # (B, 23, 3, 3)
    blocks = w.limits * D.transpose(-1, -2) @ D
    gl = w.limits * (D.transpose(-1, -2) @ exc[..., None])[..., 0]
    Hp = H[:, 6:N_POSE_PARAMS, 6:N_POSE_PARAMS].reshape(B, 23, 3, 23, 3)
    j = torch.arange(23)
    Hp[:, j, :, j, :] += blocks.transpose(0, 1)
    H[:, 6:N_POSE_PARAMS, 6:N_POSE_PARAMS] = Hp.reshape(B, 69, 69)
    g[:, 6:N_POSE_PARAMS] += gl.reshape(B, 69)
    if turn is None:
        return H, g
    # marker offsets: block-diagonal among themselves, coupled to every other column
    P = H.shape[1]
    Hpo = torch.einsum("bmjp,bmjk->bpmk", HJ, turn).reshape(B, P, M * 3)
    Hoo = turn.transpose(-1, -2) @ Hm @ turn  # (B, M, 3, 3)
    go = (turn.transpose(-1, -2) @ gm[..., None])[..., 0].reshape(B, M * 3)
    full = H.new_zeros(B, P + 3 * M, P + 3 * M)
    full[:, :P, :P] = H
    full[:, :P, P:] = Hpo
    full[:, P:, :P] = Hpo.transpose(1, 2)
    blocks = full[:, P:, P:].view(B, M, 3, M, 3)
    m = torch.arange(M)
    blocks[:, m, :, m, :] = Hoo.transpose(0, 1)
    return full, torch.cat([g, go], 1)
