"""Per-crop pseudo-3D targets from the rig's fused bodies (what `gst.train.distill` builds).

A crop of person p in frame f gets the fused body of (p, f): world joints, the body's
orientation in the world, the local joint rotations and the shape, with weights that say how
much the fit can be trusted there (0: no target). Kept apart from `gst.train.distill` so the
crop set (`gst.train.views`) can hold them without importing the fusion.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass
class DistillTargets:
    joints_world: torch.Tensor  # (N, 24, 3) metres, rig world
    joint_weight: torch.Tensor  # (N, 24) in [0, 1]: evidence per joint (views, gap-filled)
    global_orient: torch.Tensor  # (N, 3, 3) body -> world
    body_pose: torch.Tensor  # (N, 23, 3, 3) local rotations
    betas: torch.Tensor  # (N, nb)
    weight: torch.Tensor  # (N,) in [0, 1]; 0: this crop has no target
    # (N,) factors of the root and the parameters terms: below 1 where the fit guessed the
    # pelvis, or the whole torso (gap-filled: fewer than 2 views); None: 1
    root_weight: torch.Tensor | None = None
    params_weight: torch.Tensor | None = None

    def __post_init__(self):
        n = self.weight.shape[0]
        if self.root_weight is None:
            self.root_weight = torch.ones(n)
        if self.params_weight is None:
            self.params_weight = torch.ones(n)
        for f in fields(self):
            if getattr(self, f.name).shape[0] != n:
                raise ValueError(
                    f"DistillTargets.{f.name} has {getattr(self, f.name).shape[0]} rows, "
                    f"weight has {n}"
                )

    def __len__(self) -> int:
        return int(self.weight.shape[0])

    def take(self, idx: torch.Tensor) -> DistillTargets:
        return DistillTargets(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    @staticmethod
    def concat(parts: list[DistillTargets | None]) -> DistillTargets:
        if not parts:  # (parts[0] below: a bare IndexError)
            raise ValueError("DistillTargets.concat needs at least one part, got none")
        if any(p is None for p in parts):
            raise ValueError("concat_crop_sets: some crop sets have distill targets, others not")
        return DistillTargets(
            **{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(parts[0])}
        )

    @staticmethod
    def empty(n: int, num_betas: int = 10) -> DistillTargets:
        """n rows without a target (weight 0, identity rotations)."""
        eye = torch.eye(3)
        return DistillTargets(
            joints_world=torch.zeros(n, 24, 3),
            joint_weight=torch.zeros(n, 24),
            global_orient=eye.repeat(n, 1, 1),
            body_pose=eye.repeat(n, 23, 1, 1),
            betas=torch.zeros(n, num_betas),
            weight=torch.zeros(n),
        )
