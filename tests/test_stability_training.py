"""A long training run through the real rasteriser with NaN and Inf injected: the trainer's guard
skips exactly the poisoned steps (no optimiser update, counted, logged), training still
converges, and a run of consecutive bad steps aborts with a clear error while the last
checkpoint stays usable."""

from __future__ import annotations

import csv
import math

import pytest
import torch
from torch import nn

from gst.render.rasterize import rasterize
from gst.train.trainer import NonFiniteLossError, TrainConfig, Trainer

SIZE = 16
N = 24


def _cameras():
    """Two cameras 3 m from the origin, looking at it from the front and from the side."""
    front = torch.eye(4)
    front[2, 3] = 3.0
    side = torch.zeros(4, 4)
    side[:3, :3] = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # rotation about y
    side[2, 3], side[3, 3] = 3.0, 1.0
    K = torch.tensor([[25.0, 0, 7.5], [0, 25.0, 7.5], [0, 0, 1]])
    return torch.stack([front, side]), torch.stack([K, K])


class Splats(nn.Module):
    """N Gaussians with unconstrained parameters (log scales, opacity logits)."""

    def __init__(self, seed: int, spread: float = 0.25):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.means = nn.Parameter(spread * torch.randn(N, 3, generator=g))
        self.log_scales = nn.Parameter(
            torch.log(torch.full((N, 3), 0.12)) + 0.2 * torch.randn(N, 3, generator=g)
        )
        self.quats = nn.Parameter(torch.randn(N, 4, generator=g))
        self.opacity_logits = nn.Parameter(torch.zeros(N))
        self.color_logits = nn.Parameter(torch.randn(N, 3, generator=g))

    def forward(self, viewmats, Ks):
        return rasterize(
            self.means,
            self.quats,
            self.log_scales.exp(),
            torch.sigmoid(self.opacity_logits),
            torch.sigmoid(self.color_logits),
            viewmats,
            Ks,
            SIZE,
            SIZE,
            backend="torch",
        )


class Problem:
    """Fit Splats to renders of another Splats. Steps listed in `nan_target` get a target with
    NaN pixels (a corrupt frame: the loss is NaN); steps in `inf_grad` get an infinite gradient
    with a finite loss (an overflow in backward only)."""

    def __init__(self, nan_target=(), inf_grad=()):
        torch.manual_seed(0)
        self.viewmats, self.Ks = _cameras()
        with torch.no_grad():
            self.target = Splats(seed=1).forward(self.viewmats, self.Ks).rgb
        self.model = Splats(seed=2, spread=0.4)
        self.nan_target, self.inf_grad = set(nan_target), set(inf_grad)
        self.calls = 0

    def sample(self, gen: torch.Generator, batch_size: int):
        self.calls += 1
        target = self.target.clone()
        if self.calls in self.nan_target:
            target[0, 3:7, 3:7] = float("nan")
        return target, self.calls in self.inf_grad

    def step(self, model, batch):
        target, poison_grad = batch
        rgb = model(self.viewmats, self.Ks).rgb
        loss = ((rgb - target) ** 2).mean()
        if poison_grad:
            model.means.register_hook(_once(lambda g: torch.full_like(g, float("inf"))))
        return loss, {"mse": loss.detach()}

    def loss_now(self) -> float:
        with torch.no_grad():
            return float(((self.model(self.viewmats, self.Ks).rgb - self.target) ** 2).mean())


def _once(fn):
    """A tensor hook that acts on the first backward only (hooks persist on leaf parameters)."""
    state = {"done": False}

    def hook(g):
        if state["done"]:
            return g
        state["done"] = True
        return fn(g)

    return hook


def test_long_run_survives_injected_nan_and_inf(tmp_path):
    steps = 240
    nan_steps = {5, 6, 40, 41, 42, 100, 170, 239}
    inf_steps = {20, 120, 200}
    problem = Problem(nan_target=nan_steps, inf_grad=inf_steps)
    before = problem.loss_now()
    cfg = TrainConfig(
        steps=steps,
        batch_size=1,
        lr=0.02,
        warmup_steps=10,
        weight_decay=0.0,
        grad_clip=1.0,
        ckpt_every=100,
        val_every=10**6,
        log_every=1,
    )  # default max_bad_steps (20)
    trainer = Trainer(problem.model, problem.step, problem.sample, cfg, tmp_path)
    summary = trainer.fit()

    bad = len(nan_steps) + len(inf_steps)
    assert summary.steps == steps and summary.bad_steps == bad
    assert all(torch.isfinite(p).all() for p in problem.model.parameters())
    # Skipped steps do not reach the optimiser: Adam counted only the good ones.
    adam_steps = {int(s["step"]) for s in trainer.optimizer.state_dict()["state"].values()}
    assert adam_steps == {steps - bad}
    # The log marks exactly the poisoned steps as skipped.
    with open(tmp_path / "log.csv") as f:
        rows = list(csv.DictReader(f))
    skipped = {int(r["step"]) for r in rows if float(r["skipped"] or 0) == 1}
    assert skipped == nan_steps | inf_steps
    assert all(math.isfinite(float(r["loss"])) for r in rows if int(r["step"]) not in nan_steps)
    # And training still did its job.
    after = problem.loss_now()
    assert after < 0.25 * before, (before, after)
    reloaded = torch.load(tmp_path / "last.pt", weights_only=True)
    assert reloaded["trainer"]["bad_steps"] == bad
    assert all(torch.isfinite(v).all() for v in reloaded["model"].values())


@pytest.mark.parametrize("kind", ["nan_loss", "inf_grad"])
def test_consecutive_bad_steps_abort_with_a_clear_error(tmp_path, kind):
    """Healthy for 12 steps (a checkpoint at 10), then every step is bad: the run stops at the
    limit, names it, and the checkpoint on disk holds finite weights."""
    limit = 4
    poisoned = range(13, 100)
    problem = Problem(**{"nan_target" if kind == "nan_loss" else "inf_grad": poisoned})
    cfg = TrainConfig(
        steps=100,
        batch_size=1,
        lr=0.02,
        warmup_steps=2,
        max_bad_steps=limit,
        ckpt_every=10,
        val_every=10**6,
        log_every=1,
    )
    trainer = Trainer(problem.model, problem.step, problem.sample, cfg, tmp_path)
    with pytest.raises(
        NonFiniteLossError, match=rf"{limit} non-finite steps \(limit {limit}\).*learning rate"
    ):
        trainer.fit()
    assert trainer.step == 12 + limit - 1 and trainer.bad_steps == limit
    assert all(torch.isfinite(p).all() for p in problem.model.parameters())
    ckpt = torch.load(tmp_path / "last.pt", weights_only=True)
    assert ckpt["trainer"]["step"] == 10 and ckpt["trainer"]["bad_steps"] == 0
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values())
    # Resuming from that checkpoint continues with finite weights.
    fresh = Problem()
    resumed = Trainer(fresh.model, fresh.step, fresh.sample, cfg, tmp_path)
    assert resumed.resume() and resumed.step == 10


def test_one_bad_step_short_of_the_limit_finishes(tmp_path):
    limit = 4
    problem = Problem(nan_target=range(3, 3 + limit - 1))
    cfg = TrainConfig(
        steps=12, batch_size=1, lr=0.02, warmup_steps=2, max_bad_steps=limit, val_every=10**6
    )
    summary = Trainer(problem.model, problem.step, problem.sample, cfg, tmp_path).fit()
    assert summary.steps == 12 and summary.bad_steps == limit - 1


def test_log_keeps_columns_that_appear_later(tmp_path):
    """log.csv used to take its header from the first row, so a later validation or 'skipped'
    column was silently dropped."""
    problem = Problem(nan_target={4})
    cfg = TrainConfig(steps=6, batch_size=1, lr=0.02, warmup_steps=1, val_every=3, log_every=1)
    Trainer(
        problem.model, problem.step, problem.sample, cfg, tmp_path, val_fn=lambda m: {"score": 0.5}
    ).fit()
    with open(tmp_path / "log.csv") as f:
        rows = {int(r["step"]): r for r in csv.DictReader(f)}
    assert sorted(rows) == [1, 2, 3, 4, 5, 6]
    assert float(rows[3]["val_score"]) == 0.5 and float(rows[6]["val_score"]) == 0.5
    assert (
        rows[1]["val_score"] == "" and float(rows[4]["skipped"]) == 1 and rows[5]["skipped"] == ""
    )
