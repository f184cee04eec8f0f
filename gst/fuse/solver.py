"""Batched Levenberg-Marquardt over person-frames with per-person shape (Schur complement).

The unknowns are, per person-frame, the root rotation, translation and 23 local rotations
(gst.body.kinematics), and per person the betas. The normal equations of one person are block
arrowhead: one 75 x 75 block per frame, coupled only through the betas. Eliminating the frames
(Schur complement) leaves an nb x nb system per person, so one iteration costs a batched Cholesky
of the frame blocks plus a tiny solve per person: linear in frames x people.

Damping is per person (Marquardt's scaling by the diagonal); a step is kept for a person when
their total energy drops, else that person's damping grows and their step is retried from the
same linearisation (people already moved keep their step).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from gst.body.kinematics import N_POSE_PARAMS, rodrigues

__all__ = ["BodyState", "levenberg_marquardt", "schur_step"]


@dataclass
class BodyState:
    root: torch.Tensor  # (B, 3, 3) body -> world
    transl: torch.Tensor  # (B, 3)
    theta: torch.Tensor  # (B, 23, 3) local axis-angle
    betas: torch.Tensor  # (people, nb)
    offsets: torch.Tensor | None = None  # (people, M, 3) the person's own marker offsets

    def person_params(self) -> torch.Tensor:
        """(people, Q): betas, then the marker offsets if they are unknowns."""
        if self.offsets is None:
            return self.betas
        return torch.cat([self.betas, self.offsets.flatten(1)], 1)

    def step(self, dp: torch.Tensor, dq: torch.Tensor) -> BodyState:
        nb = self.betas.shape[1]
        return BodyState(
            rodrigues(dp[:, :3]) @ self.root,
            self.transl + dp[:, 3:6],
            self.theta + dp[:, 6:N_POSE_PARAMS].reshape(self.theta.shape),
            self.betas + dq[:, :nb],
            None if self.offsets is None else self.offsets + dq[:, nb:].reshape(self.offsets.shape),
        )

    def where(self, keep_frame: torch.Tensor, keep_person: torch.Tensor, other: BodyState):
        """Rows of self where keep_*, else of other."""
        f = keep_frame
        return BodyState(
            torch.where(f[:, None, None], self.root, other.root),
            torch.where(f[:, None], self.transl, other.transl),
            torch.where(f[:, None, None], self.theta, other.theta),
            torch.where(keep_person[:, None], self.betas, other.betas),
            None
            if self.offsets is None
            else torch.where(keep_person[:, None, None], self.offsets, other.offsets),
        )


def _per_person(x: torch.Tensor, person: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros((n,) + x.shape[1:], dtype=x.dtype).index_add_(0, person, x)


def schur_step(
    H: torch.Tensor,
    g: torch.Tensor,
    betas: torch.Tensor,
    person: torch.Tensor,
    lam: torch.Tensor,
    w_betas: float | torch.Tensor,
    frozen_betas: bool = False,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The damped Gauss-Newton step (dp (B, 75), db (people, Q)) of the whole problem

        [blockdiag(A_t) + D    B      ] [dp]     [g_t                    ]
        [B^T                   S + D  ] [db] = - [sum_t g_b,t + w_b betas]

    with each person's parameters (`betas` (people, Q): the betas, and the marker offsets when
    they are unknowns; prior weights `w_betas`, a number or (Q,)) shared by their frames, by
    eliminating the frame blocks; D is Marquardt's damping lam x diag. None if a damped frame
    block is not positive definite."""
    n, nb = betas.shape
    P = N_POSE_PARAMS
    A, Bm, C = H[:, :P, :P], H[:, :P, P:], H[:, P:, P:]
    ga, gb = g[:, :P], g[:, P:]
    Ad = A + torch.diag_embed(lam[person, None] * torch.diagonal(A, dim1=1, dim2=2) + 1e-9)
    L, info = torch.linalg.cholesky_ex(Ad)
    if bool((info != 0).any()):
        return None
    sol = torch.cholesky_solve(torch.cat([Bm, ga[..., None]], -1), L)
    AiB, Aig = sol[..., :nb], sol[..., nb]
    if frozen_betas:
        db = torch.zeros_like(betas)
    else:
        S = _per_person(C - Bm.transpose(1, 2) @ AiB, person, n)
        S = S + torch.diag_embed(torch.as_tensor(w_betas, dtype=H.dtype).expand(nb))
        rhs = _per_person(gb - (Bm.transpose(1, 2) @ Aig[..., None])[..., 0], person, n)
        rhs = rhs + w_betas * betas
        S = S + torch.diag_embed(lam[:, None] * torch.diagonal(S, dim1=1, dim2=2) + 1e-9)
        db = -torch.linalg.solve(S, rhs[..., None])[..., 0]
    dp = -(Aig + (AiB @ db[person][..., None])[..., 0])
    return dp, db


def levenberg_marquardt(
    state: BodyState,
    person: torch.Tensor,
    energy: Callable[[BodyState], torch.Tensor],
    linearise: Callable[[BodyState], tuple[torch.Tensor, torch.Tensor]],
    iterations: int,
    w_betas: float | torch.Tensor,
    damping: float = 1e-3,
    retries: int = 6,
    frozen_betas: bool = False,
) -> BodyState:
    """Minimise sum(energy(state)) + sum(w_betas * person_params^2).

    energy(state) -> (B,) per person-frame; linearise(state) -> H (B, P, P), g (B, P) with
    P = 75 + Q (the person's parameters last) in the E ~ E0 + 2 g.dp + dp.H.dp convention.
    """
    n = state.betas.shape[0]

    def total(s: BodyState) -> torch.Tensor:
        return _per_person(energy(s), person, n) + (w_betas * s.person_params() ** 2).sum(-1)

    lam = torch.full((n,), damping, dtype=state.theta.dtype)
    current = total(state)
    for _ in range(iterations):
        H, g = linearise(state)
        pending = torch.ones(n, dtype=torch.bool)  # people still looking for a step
        for _ in range(retries):
            step = schur_step(H, g, state.person_params(), person, lam, w_betas, frozen_betas)
            if step is None:  # a frame block is not positive definite: damp harder
                lam = lam * 10
                continue
            dp, db = step
            trial = state.step(dp, db)
            new = total(trial)
            ok = (new < current) & pending
            state = trial.where(ok[person], ok, state)
            current = torch.where(ok, new, current)
            lam = torch.where(ok, lam * 0.2, torch.where(pending, lam * 10, lam)).clamp(1e-9, 1e9)
            pending = pending & ~ok
            if not bool(pending.any()):
                break
    return state
