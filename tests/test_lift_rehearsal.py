"""Rehearsal of the landmark prior during multi-view training (gst.lift.rehearsal): its batches
follow the trainer's generator (so a resumed run is the uninterrupted one), its loss trains the
landmark path, and train_scene refuses a rehearsal weight it cannot honour."""

from __future__ import annotations

import csv
import math

import pytest
import torch

from gst.body import load_body_model
from gst.lift.rehearsal import PriorRehearsal
from gst.model.presets import get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.trainer import TrainConfig
from tests.test_train_recipe import crop_set


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


def _net(body, seed=0):
    torch.manual_seed(seed)
    return build_network(get_preset("tiny", landmark_tokens=True), body)


def test_draws_follow_the_generator(body):
    net, _, _ = _net(body)
    r = PriorRehearsal(body, net, batch_size=4)
    gen = torch.Generator().manual_seed(5)
    a = r.draw(gen)
    # the trainer's generator is read, not drawn from: the scene's batches stay the same
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(5).get_state())
    r.draw(torch.Generator().manual_seed(6))  # the sampler's own state does not carry over
    b = r.draw(torch.Generator().manual_seed(5))
    c = r.draw(torch.Generator().manual_seed(6))
    assert torch.equal(a.landmarks, b.landmarks) and torch.equal(a.joints_cam, b.joints_cam)
    assert not torch.equal(a.joints_cam, c.joints_cam)


def test_the_loss_reaches_the_landmark_path_and_is_weighted(body):
    net, _, _ = _net(body)
    lift = PriorRehearsal(body, net, batch_size=4).draw(torch.Generator().manual_seed(1))
    one, parts = PriorRehearsal(body, net, weight=1.0, batch_size=4).terms(net, lift)
    half, _ = PriorRehearsal(body, net, weight=0.5, batch_size=4).terms(net, lift)
    assert math.isfinite(float(one.detach())) and float(one.detach()) > 0
    assert float(half.detach()) == pytest.approx(0.5 * float(one.detach()), rel=1e-5)
    assert parts["rehearsal_mpjpe_mm"] > 0
    one.backward()
    grads = [p.grad for p in net.landmark_encoder.parameters()]
    assert any(g is not None and g.abs().sum() > 0 for g in grads)
    assert all(p.grad is None for p in net.backbone.parameters())  # no image was seen


def test_bad_settings_are_refused(body):
    net, _, _ = _net(body)
    with pytest.raises(ValueError, match="weight > 0"):
        PriorRehearsal(body, net, weight=0.0)
    plain, _, _ = build_network(get_preset("tiny"), body)
    with pytest.raises(ValueError, match="landmark tokens"):
        PriorRehearsal(body, plain)


class _Recording(PriorRehearsal):
    """Remembers a fingerprint of every batch it draws."""

    def __post_init__(self):
        super().__post_init__()
        self.seen: list[tuple[float, float]] = []

    def draw(self, generator):
        lift = super().draw(generator)
        self.seen.append((float(lift.joints_cam.sum()), float(lift.landmarks.nansum())))
        return lift


def _fit(body, out, steps):
    net, ids, groups = _net(body)
    crops = crop_set()
    task = make_task(body, ids, net.cfg, crops.crop_size, LossWeights(lpips=0.0))
    rehearsal = _Recording(body, net, weight=1.0, batch_size=4)
    fit_gst(
        net, task, crops,
        TrainConfig(steps=steps, batch_size=2, warmup_steps=1, val_every=10, log_every=1,
                    ckpt_every=1),
        out,
        FitOptions(mode="multiview", num_targets=2, render_size=16, heldout_cameras=("c2",)),
        body_spec="anny", vertex_ids=ids, group_index=groups, rehearsal=rehearsal,
    )  # fmt: skip
    return rehearsal.seen


def test_a_resumed_fit_rehearses_what_an_uninterrupted_one_does(body, tmp_path):
    whole = _fit(body, tmp_path / "whole", steps=3)
    first = _fit(body, tmp_path / "cut", steps=2)
    rest = _fit(body, tmp_path / "cut", steps=3)  # resumes from the step-2 checkpoint
    assert len(whole) == 3 and len(set(whole)) == 3  # a fresh batch every step
    assert first + rest == whole
    rows = list(csv.DictReader(open(tmp_path / "whole" / "log.csv")))
    assert len(rows) == 3 and all(float(r["rehearsal"]) > 0 for r in rows)
    assert all(float(r["rehearsal_mpjpe_mm"]) > 0 for r in rows)


def _median_tilt_deg(lift) -> float:
    """Median angle between each body's pelvis-to-neck axis and the world's up (+z)."""
    up = lift.R[:, :, 2]  # the world's +z in each camera
    axis = lift.joints_cam[:, 12] - lift.joints_cam[:, 0]
    cos = (axis * up).sum(-1) / axis.norm(dim=-1)
    return float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).median())


def test_rehearsal_leans_bodies_as_the_pretraining_did(body):
    """The rehearsed prior is the pretrained one: its bodies lean with the recipe's spread."""
    from dataclasses import replace

    from gst.lift.pretrain import LiftPretrainConfig

    net, _, _ = _net(body)
    tilt = {
        lean: _median_tilt_deg(
            PriorRehearsal(
                body, net, batch_size=64, recipe=replace(LiftPretrainConfig(), lean_deg=lean)
            ).draw(torch.Generator().manual_seed(2))
        )
        for lean in (0.0, 40.0)
    }
    assert tilt[40.0] > tilt[0.0] + 15.0, tilt
