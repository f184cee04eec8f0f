"""The generic training loop: exact resume after a kill, NaN guard, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from gst.train.trainer import NonFiniteLossError, TrainConfig, Trainer, warmup_cosine


class Killed(Exception):
    pass


def make_problem(kill_at: int | None = None, nan_every: int | None = None):
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(4, 8), nn.Tanh(), nn.Linear(8, 1))
    w_true = torch.tensor([[1.0], [-2.0], [0.5], [3.0]])
    calls = {"n": 0}

    def sample(gen: torch.Generator, bs: int):
        x = torch.randn(bs, 4, generator=gen)
        return x, x @ w_true

    def step(m, batch):
        calls["n"] += 1
        if kill_at is not None and calls["n"] == kill_at:
            raise Killed()
        x, y = batch
        loss = ((m(x) - y) ** 2).mean()
        if nan_every and calls["n"] % nan_every == 0:
            loss = loss * float("nan")
        return loss, {"mse": loss.detach()}

    return model, step, sample


def test_resume_after_kill_is_exact(tmp_path):
    cfg = TrainConfig(
        steps=12, batch_size=4, lr=1e-2, warmup_steps=3, ckpt_every=5, val_every=100, log_every=1
    )
    model, step, sample = make_problem()
    Trainer(model, step, sample, cfg, tmp_path / "a").fit()
    reference = [p.detach().clone() for p in model.parameters()]

    model_b, step_b, sample_b = make_problem(kill_at=8)
    with pytest.raises(Killed):
        Trainer(model_b, step_b, sample_b, cfg, tmp_path / "b").fit()
    model_c, step_c, sample_c = make_problem()  # fresh process: new model, resumes from last.pt
    trainer = Trainer(model_c, step_c, sample_c, cfg, tmp_path / "b")
    assert trainer.resume()
    assert trainer.step == 5
    opt_state = trainer.optimizer.state_dict()["state"]
    assert opt_state and all(int(s["step"]) == 5 for s in opt_state.values())
    trainer.fit()
    for a, b in zip(reference, model_c.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # The log holds every step once, in order (the killed run had logged steps 6-7 past its
    # last checkpoint), and its clock continues across the resume instead of restarting.
    import csv

    rows = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, 13))
    seconds = [float(r["seconds"]) for r in rows]
    assert seconds == sorted(seconds)
    # and the model file does not depend on wall-clock time
    a = torch.load(tmp_path / "a" / "last.pt", weights_only=True)["trainer"]
    assert "seconds" not in a


def test_nan_guard_skips_and_aborts(tmp_path):
    cfg = TrainConfig(
        steps=10, batch_size=4, lr=1e-2, warmup_steps=1, max_bad_steps=100, log_every=1
    )
    model, step, sample = make_problem(nan_every=3)
    summary = Trainer(model, step, sample, cfg, tmp_path).fit()
    assert summary.bad_steps == 3
    assert all(torch.isfinite(p).all() for p in model.parameters())
    cfg.max_bad_steps = 2
    model, step, sample = make_problem(nan_every=2)
    with pytest.raises(NonFiniteLossError):
        Trainer(model, step, sample, cfg, tmp_path / "x").fit()


def test_a_nan_validation_value_is_never_the_best(tmp_path):
    """Validations nan, 50, 10, 5 (lower is better): the NaN became the best, every later
    comparison with it was false, and best.pt stayed the step-2 model."""
    cfg = TrainConfig(steps=8, batch_size=4, lr=1e-2, warmup_steps=1, val_every=2, log_every=1)
    model, step, sample = make_problem()
    values = iter([float("nan"), 50.0, 10.0, 5.0])
    trainer = Trainer(
        model, step, sample, cfg, tmp_path,
        val_fn=lambda m: {"mpjpe": next(values)}, best_key="mpjpe", best_mode="min",
    )  # fmt: skip
    summary = trainer.fit()
    assert summary.best == 5.0
    assert torch.load(tmp_path / "best.pt", weights_only=True)["trainer"]["step"] == 8


def test_a_resume_with_other_settings_says_which(tmp_path, caplog):
    """A library caller resuming into the same folder with another learning rate continued
    last.pt's run without a word (the pipeline starts a changed run in a fresh folder)."""
    from dataclasses import replace

    cfg = TrainConfig(steps=6, batch_size=4, lr=1e-2, warmup_steps=1, ckpt_every=3, log_every=1)
    model, step, sample = make_problem()
    Trainer(model, step, sample, cfg, tmp_path).fit()
    with caplog.at_level("WARNING", logger="gst.train"):
        model, step, sample = make_problem()
        Trainer(model, step, sample, replace(cfg, ckpt_every=2), tmp_path).resume()
    assert "other settings" not in caplog.text  # bookkeeping only
    with caplog.at_level("WARNING", logger="gst.train"):
        model, step, sample = make_problem()
        Trainer(model, step, sample, replace(cfg, lr=5e-3), tmp_path).resume()
    assert "written with other settings: lr: 0.01 -> 0.005" in caplog.text


def test_a_foreign_last_checkpoint_is_named(tmp_path):
    """A copied, cut or foreign last.pt failed with a bare RuntimeError or KeyError 101."""
    cfg = TrainConfig(steps=2, batch_size=4, lr=1e-2, warmup_steps=1, ckpt_every=1, log_every=1)
    model, step, sample = make_problem()
    trainer = Trainer(model, step, sample, cfg, tmp_path)
    for content, message in ((b"not a checkpoint\n", "cannot resume from it"), (None, "no model")):
        if content is None:
            torch.save({"weights": torch.ones(2)}, trainer.last_path)
        else:
            trainer.last_path.write_bytes(content)
        with pytest.raises(ValueError, match=f"last.pt: .*{message}.*delete it to start afresh"):
            trainer.resume()


def test_schedule_warms_up_then_decays():
    cfg = TrainConfig(steps=100, warmup_steps=10, min_lr_ratio=0.1)
    values = [warmup_cosine(s, cfg.steps, cfg.warmup_steps, cfg.min_lr_ratio) for s in range(100)]
    assert values[0] == pytest.approx(0.1) and values[9] == pytest.approx(1.0)
    assert all(b <= a + 1e-12 for a, b in zip(values[10:], values[11:], strict=False))
    assert values[-1] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 89 / 90)))


def test_log_rows_give_the_rate_their_step_used(tmp_path):
    """log.csv's `lr` was the next step's rate (read after the scheduler stepped)."""
    import csv

    model, used = nn.Linear(2, 1), []

    def step(m, x):
        used.append(trainer.optimizer.param_groups[0]["lr"])  # what optimizer.step() applies
        return (m(x) ** 2).mean(), {}

    cfg = TrainConfig(
        steps=6,
        batch_size=2,
        lr=1.0,
        warmup_steps=3,
        min_lr_ratio=0.05,
        ckpt_every=100,
        val_every=100,
        log_every=1,
    )
    trainer = Trainer(model, step, lambda g, b: torch.randn(b, 2, generator=g), cfg, tmp_path)
    trainer.fit()
    logged = [float(r["lr"]) for r in csv.DictReader(open(tmp_path / "log.csv"))]
    assert logged == pytest.approx(used) and len(used) == 6


def test_resuming_another_networks_last_checkpoint_names_the_file(tmp_path):
    """A library caller resuming a folder whose last.pt is another network's got torch's bare
    "size mismatch" RuntimeError; now a ValueError that names the file and the way out."""
    cfg = TrainConfig(steps=2, batch_size=4, lr=1e-2, warmup_steps=1, ckpt_every=1, log_every=1)
    model, step, sample = make_problem()
    Trainer(model, step, sample, cfg, tmp_path).fit()
    wider = nn.Sequential(nn.Linear(4, 16), nn.Tanh(), nn.Linear(16, 1))
    with pytest.raises(ValueError, match=r"last\.pt: a checkpoint of another network.*delete it"):
        Trainer(wider, step, sample, cfg, tmp_path).resume()


def test_resuming_with_other_optimiser_groups_names_the_file_and_changes_nothing(tmp_path):
    """The model loaded, then the optimiser refused the file with torch's bare "loaded state
    dict has a different number of parameter groups", naming no file (e.g. body_lr set on a
    run that had none)."""
    cfg = TrainConfig(steps=2, batch_size=4, lr=1e-2, warmup_steps=1, ckpt_every=1, log_every=1)
    model, step, sample = make_problem()
    Trainer(model, step, sample, cfg, tmp_path).fit()
    fresh, step, sample = make_problem()
    before = {k: v.clone() for k, v in fresh.state_dict().items()}
    groups = [
        {"params": fresh[0].parameters(), "lr": 1e-2},
        {"params": fresh[2].parameters(), "lr": 1e-3},
    ]
    trainer = Trainer(fresh, step, sample, cfg, tmp_path, param_groups=groups)
    with pytest.raises(
        ValueError,
        match=r"last\.pt: its optimiser state does not fit .*\[4\] in the file, "
        r"\[2, 2\] in this run.*delete it to start afresh",
    ):
        trainer.resume()
    assert trainer.step == 0
    assert all(torch.equal(v, before[k]) for k, v in fresh.state_dict().items())


def test_a_damaged_rank_state_draws_a_fresh_stream_with_a_word(tmp_path, caplog):
    """A rank's own generator state cut short (a disk filled) raised an unpickling traceback on
    resume; a missing one drew a fresh stream with a warning: so does a damaged one now."""
    from types import SimpleNamespace

    from gst.train.trainer import Trainer

    path = tmp_path / "last.rank1.pt"
    path.write_bytes(b"PK\x03\x04 cut short")
    rank = SimpleNamespace(
        rank_state_path=path, step=5, rank=1, generator=torch.Generator(),
        cfg=SimpleNamespace(seed=0),
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="gst.train"):
        Trainer._resume_rank_state(rank)
    assert any("cannot read" in m for m in caplog.messages)
    assert any("drawing a fresh stream" in m for m in caplog.messages)


def test_no_runs_rank_draws_another_runs_stream():
    """Each rank's batch generator was seeded seed + 1000 * rank: seed 1000's rank 0 drew the
    batches of seed 0's rank 1. A single process (rank 0) keeps its seed."""
    from gst.train.trainer import rank_seed

    assert rank_seed(7, 0) == 7
    seeds = {(s, r): rank_seed(s, r) for s in (0, 1, 999, 1000, 2000) for r in range(4)}
    assert len(set(seeds.values())) == len(seeds)
    fresh = {rank_seed(0, r, step) for r in range(3) for step in range(50)}
    assert len(fresh) == 150 and not fresh & set(seeds.values())
    assert 0 <= rank_seed(-3, 2) < 2**63  # torch takes it


@pytest.mark.parametrize("key", ["scheduler", "generator", "torch_rng"])
def test_a_last_checkpoint_missing_trainer_state_is_refused_before_loading(tmp_path, key):
    """A last.pt whose trainer state lacked the scheduler, generator or RNG state failed with a
    bare KeyError after the model's weights and the optimiser were loaded (half resumed)."""
    cfg = TrainConfig(steps=2, batch_size=4, lr=1e-2, warmup_steps=1, ckpt_every=1, log_every=1)
    model, step, sample = make_problem()
    trainer = Trainer(model, step, sample, cfg, tmp_path)
    trainer.fit()
    ckpt = torch.load(trainer.last_path, weights_only=True)
    del ckpt["trainer"][key]
    torch.save(ckpt, trainer.last_path)
    fresh, step, sample = make_problem()
    before = {k: v.clone() for k, v in fresh.state_dict().items()}
    again = Trainer(fresh, step, sample, cfg, tmp_path)
    with pytest.raises(ValueError, match=rf"last\.pt: .*'{key}'.*delete it to start afresh"):
        again.resume()
    assert again.step == 0 and not again.optimizer.state_dict()["state"]
    assert all(torch.equal(v, before[k]) for k, v in fresh.state_dict().items())
