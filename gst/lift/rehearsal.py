"""Rehearsal of the render-free landmark prior while GST trains on a scene.

Multi-view training on one scene (the demo: two synthetic people, 36 frames) pulls the shared
SMPL head towards those people, cameras and motions, and without a reminder it forgets part of
the prior that the render-free pretraining (gst.lift.pretrain) taught it on sampled bodies: the
demo's trained model was 5-15 mm worse than its pretrained start on people it never saw (the
real lab capture against its fused bodies, two synthetic crowd scenes against their truth;
docs/training.md, "Prior rehearsal").

`PriorRehearsal` adds, to every training step, the pretraining's own supervised terms on a
fresh batch of simulated detections (gst.lift.sampler), through the network's landmark-only
mode, weighted by `weight`. The batch is drawn in the trainer's sampling function, seeded by the
state of the trainer's generator (without drawing from it), so a resumed run draws the same
batches as an uninterrupted one and the scene's own batches are those of a run without it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import torch

from gst.body import BodyModel
from gst.device import model_device, module_on
from gst.lift.pretrain import LiftPretrainConfig, landmark_set_of, lift_terms
from gst.lift.sampler import LiftBatch
from gst.model.network import GSTNetwork

__all__ = ["PriorRehearsal"]


@dataclass
class PriorRehearsal:
    """gst.train.recipe's `Rehearsal`: `draw(generator)` -> a simulated batch; `terms(model,
    lift)` -> (weighted loss, metrics)."""

    body: BodyModel
    net: GSTNetwork
    weight: float = 1.0
    batch_size: int = 32
    crop_size: int = 256
    # the pretraining's sampled bodies and loss weights (the same prior is rehearsed)
    recipe: LiftPretrainConfig = field(default_factory=LiftPretrainConfig)
    _bodies: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.net.landmark_encoder is None:
            raise ValueError("prior rehearsal needs a network with landmark tokens")
        if self.weight <= 0 or self.batch_size < 1:
            raise ValueError(
                f"prior rehearsal: weight > 0 and batch_size >= 1, got {self.weight}, "
                f"{self.batch_size}"
            )
        self.sampler = self.recipe.sampler(
            self.body, landmark_set_of(self.net).name, crop_size=self.crop_size
        )

    def draw(self, generator: torch.Generator) -> LiftBatch:
        """A fresh simulated batch, seeded by the state of the trainer's `generator` without
        drawing from it: the scene's batches stay those of a run without rehearsal, and a
        resumed run (whose generator state the checkpoint restores) draws the same."""
        state = generator.get_state().numpy().tobytes()
        seed = int.from_bytes(hashlib.blake2b(state, digest_size=8).digest(), "little") >> 2
        self.sampler.gen.manual_seed(seed)
        return self.sampler.sample(self.batch_size)

    def terms(self, model, lift: LiftBatch) -> tuple[torch.Tensor, dict]:
        # the sampler keeps its CPU body; the terms need one where the model trains (one copy)
        device = model_device(model)
        if device not in self._bodies:
            self._bodies[device] = module_on(self.body, device)
        terms, error_mm = lift_terms(model, self._bodies[device], lift, self.recipe.weights)
        return self.weight * terms.total, {
            "rehearsal": terms.total.detach(),
            "rehearsal_mpjpe_mm": error_mm,
        }
