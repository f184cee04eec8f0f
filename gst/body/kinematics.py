"""Joints-only body forward with analytic Jacobians: what the body fit evaluates every iteration.

The fit needs the virtual markers (gst.body.markers) of a posed body and their derivatives, not
the mesh. Rest joints are linear in the shape (`J_template + J_shapedirs @ betas`, precomputed
by gst.body.BodyModel), forward kinematics runs over the 24 joints only, and each marker is
`J[anchor] + G[frame] @ offset`. For B person-frames this costs a few small batched products.

Parameters per person-frame (P = 75 + nb columns of the Jacobian):

    [0:3]    root rotation increment, world axis, about the root joint (R_root <- exp(d) R_root)
    [3:6]    translation (metres)
    [6:75]   local joint rotations theta (23 x 3 axis-angle, SMPL axes, parent frame)
    [75:]    betas (shared by a person's frames; the fit eliminates them by a Schur complement)

Derivatives: rotating joint j by a small world-axis angle w moves every point rigidly attached
below it by w x (X - J_j); with R_j = exp(theta_j), d theta_j turns the child by the world axis
w = G_parent(j) J_l(theta_j) d theta_j (J_l: SO(3) left Jacobian). A marker moves with joint j
when j is a strict ancestor of its anchor (its anchor moves) or an ancestor-or-self of its frame
joint (its offset turns). The betas move each joint through the rest bones along its chain.
"""

from __future__ import annotations

import numpy as np
import torch

from gst.body.markers import MarkerModel
from gst.body.model import BodyModel
from gst.body.skeleton import kinematic_levels

__all__ = [
    "MarkerSkeleton",
    "pose_markers",
    "tree_levels",
    "rodrigues",
    "skew",
    "left_jacobian",
    "N_POSE_PARAMS",
]

N_POSE_PARAMS = 75  # root increment 3 + translation 3 + 23 x 3 local rotations


def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def _sinc_terms(v: torch.Tensor):
    t2 = (v * v).sum(-1)[..., None, None]
    t = torch.sqrt(t2 + 1e-30)
    # Taylor branches below a threshold where the closed forms cancel: in float32, 1 - cos t
    # is 0 below 3e-4 rad and t - sin t keeps few digits below 0.1 rad.
    small = t2 < (1e-8 if v.dtype == torch.float64 else 1e-2)
    return t2, t, small


def _one_minus_cos_over_t2(t2: torch.Tensor, t: torch.Tensor, small: torch.Tensor):
    half = torch.sin(t / 2) / (t + 1e-30)  # (1 - cos t) / t^2 = 2 sin^2(t/2) / t^2: no cancelling
    return torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, 2 * half * half)


def rodrigues(v: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3) -> rotation matrices (..., 3, 3)."""
    t2, t, small = _sinc_terms(v)
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    b = _one_minus_cos_over_t2(t2, t, small)
    K = skew(v)
    return torch.eye(3, dtype=v.dtype, device=v.device) + a * K + b * (K @ K)


def left_jacobian(v: torch.Tensor) -> torch.Tensor:
    """SO(3) left Jacobian (..., 3, 3): exp(v + dv) = exp(J_l(v) dv) exp(v) to first order."""
    t2, t, small = _sinc_terms(v)
    a = _one_minus_cos_over_t2(t2, t, small)
    b = torch.where(
        small, 1.0 / 6 - t2 / 120 + t2 * t2 / 5040, (t - torch.sin(t)) / (t2 * t + 1e-30)
    )
    K = skew(v)
    return torch.eye(3, dtype=v.dtype, device=v.device) + a * K + b * (K @ K)


def tree_levels(parents: list[int] | np.ndarray) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(joints, their parents) per depth of a kinematic tree below the root, for `pose_markers`."""
    parents = [int(p) for p in parents]
    return [
        (torch.as_tensor(level), torch.as_tensor([parents[j] for j in level]))
        for level in kinematic_levels(parents)[1:]
    ]


def pose_markers(
    rest: torch.Tensor,
    root: torch.Tensor,
    local: torch.Tensor,
    transl: torch.Tensor,
    levels: list[tuple[torch.Tensor, torch.Tensor]],
    parent_index: torch.Tensor,
    anchor: torch.Tensor,
    frame: torch.Tensor,
    offsets: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Joints-only forward kinematics and the markers on them: rest joints (B, J, 3), root
    rotation (B, 3, 3), local rotations of joints 1.. (B, J-1, 3, 3), translation (B, 3) ->
    markers (B, M, 3) = J[anchor] + G[frame] @ offset, joints (B, J, 3), world rotations
    (B, J, 3, 3) and the turned offsets G[frame] @ offset (B, M, 3); one batched product per
    depth of the tree (`tree_levels`)."""
    B, n = local.shape[0], rest.shape[1]
    bone = rest - rest[:, parent_index]  # (B, J, 3), root row unused
    G = root[:, None].expand(B, n, 3, 3)
    J = rest[:, :1].expand(B, n, 3)
    for level, par in levels:
        Rp = G[:, par]  # (B, k, 3, 3)
        G = G.index_copy(1, level, Rp @ local[:, level - 1])
        J = J.index_copy(1, level, J[:, par] + (Rp @ bone[:, level, :, None])[..., 0])
    J = J + transl[:, None]
    turned = (G[:, frame] @ offsets[..., None])[..., 0]
    return J[:, anchor] + turned, J, G, turned


class MarkerSkeleton:
    """A body model's skeleton and a marker table, evaluated with or without Jacobians."""

    def __init__(
        self,
        body: BodyModel,
        markers: MarkerModel,
        num_betas: int,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if not 0 < num_betas <= body.num_betas:
            raise ValueError(f"num_betas must be in 1..{body.num_betas}, got {num_betas}")
        if body.num_joints != 24:
            raise ValueError(f"the fit needs the 24-joint SMPL layout, got {body.num_joints}")
        self.dtype = dtype
        self.nb = num_betas
        self.J0 = body.J_template.detach().to(dtype)
        self.S = body.J_shapedirs[..., :num_betas].detach().to(dtype)  # (24, 3, nb)
        self.parents = [int(p) for p in body.parents]
        self.anchor = markers.anchors.long()
        self.frame = markers.frames.long()
        self.offsets = markers.offsets.detach().to(dtype)
        chain = [[0]]
        for j in range(1, 24):
            chain.append(chain[self.parents[j]] + [j])
        M = len(self.anchor)
        moves_anchor = np.zeros((M, 24), bool)
        turns_offset = np.zeros((M, 24), bool)
        for m in range(M):
            moves_anchor[m, chain[int(self.anchor[m])][:-1]] = True
            turns_offset[m, chain[int(self.frame[m])]] = True
        # only joints 1..23 carry local rotations; (m, j) pairs where the marker depends on j
        self._pairs = np.argwhere(moves_anchor[:, 1:] | turns_offset[:, 1:])
        self._pa = torch.as_tensor(moves_anchor[:, 1:][tuple(self._pairs.T)], dtype=dtype)
        self._parent_index = torch.as_tensor([max(p, 0) for p in self.parents])
        self._levels = tree_levels(self.parents)
        self._dbone = self.S - self.S[self._parent_index]  # (24, 3, nb) rest bone per beta
        self._po = torch.as_tensor(turns_offset[:, 1:][tuple(self._pairs.T)], dtype=dtype)

    @property
    def num_params(self) -> int:
        return N_POSE_PARAMS + self.nb

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        return self.J0 + torch.einsum("bl,jkl->bjk", betas, self.S)

    def forward(
        self,
        betas: torch.Tensor,
        root: torch.Tensor,
        theta: torch.Tensor,
        transl: torch.Tensor,
        jacobian: bool = False,
        offsets: torch.Tensor | None = None,
    ):
        """betas (B, nb), root (B, 3, 3), theta (B, 23, 3), transl (B, 3) ->
        markers (B, M, 3), joints (B, 24, 3), world rotations (B, 24, 3, 3), local rotations
        (B, 23, 3, 3), and with `jacobian` d markers / d params (B, M, 3, P). `offsets` (B, M, 3)
        replaces the table's offsets (a person's own markers); d markers / d offsets is
        G[:, frame] (the marker's frame rotation), left to the caller."""
        B = theta.shape[0]
        local = rodrigues(theta)
        off = self.offsets if offsets is None else offsets
        X, J, G, turned = pose_markers(
            self.rest_joints(betas), root, local, transl, self._levels, self._parent_index,
            self.anchor, self.frame, off,
        )  # fmt: skip
        if not jacobian:
            return X, J, G, local
        dshape = self.S[0].expand(B, 24, 3, self.nb)
        for level, par in self._levels:  # the rest bones' shape derivatives, down the tree
            dshape = dshape.index_copy(1, level, dshape[:, par] + G[:, par] @ self._dbone[level])
        M = X.shape[1]
        dX = X.new_zeros(B, M, 3, self.num_params)
        dX[..., 0:3] = -skew(X - J[:, :1])
        dX[..., 3:6] = torch.eye(3, dtype=X.dtype)
        W = G[:, self.parents[1:]] @ left_jacobian(theta)  # (B, 23, 3, 3) world axes per dtheta
        m, j = self._pairs[:, 0], self._pairs[:, 1]
        lever = (
            self._pa[:, None] * (J[:, self.anchor[m]] - J[:, 1 + j])
            + self._po[:, None] * (turned[:, m])
        )  # (B, n, 3): what the rotation of joint j swings, for each dependent marker
        d = -skew(lever) @ W[:, j]  # (B, n, 3, 3)
        dpose = X.new_zeros(B, M, 3, 23, 3)
        dpose[:, m, :, j, :] = d.transpose(0, 1)  # advanced indices go first: (n, B, 3, 3)
        dX[..., 6:N_POSE_PARAMS] = dpose.reshape(B, M, 3, 69)
        dX[..., N_POSE_PARAMS:] = dshape[:, self.anchor]
        return X, J, G, local, dX
