"""DDP under the Trainer: 2 CPU processes (gloo) give the single-process gradients of the
combined batch, and only rank 0 writes checkpoints and logs."""

from __future__ import annotations

import json
import socket

import torch
import torch.multiprocessing as tmp

from gst.train.trainer import Trainer
from tests.scaleout_items import (
    COMBINED_BATCH,
    ddp_batches_rank_main,
    ddp_config,
    ddp_problem,
    ddp_rank_main,
    ddp_step,
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_gloo_ranks_match_single_process_gradients(tmp_path, monkeypatch):
    out = tmp_path / "ddp"
    out.mkdir()
    tmp.spawn(ddp_rank_main, args=(2, _free_port(), str(out)), nprocs=2, join=True)

    monkeypatch.delenv("WORLD_SIZE", raising=False)
    model, x, y = ddp_problem()

    cfg = ddp_config(COMBINED_BATCH)
    single = Trainer(model, ddp_step, lambda gen, bs: (x, y), cfg, tmp_path / "single")
    assert single.world == 1
    single.fit()
    reference = {n: p.grad for n, p in model.named_parameters()}
    for rank in (0, 1):
        grads = torch.load(out / f"grads-rank{rank}.pt", weights_only=True)
        assert grads.keys() == reference.keys()
        for n, g in grads.items():
            torch.testing.assert_close(
                g, reference[n], rtol=1e-5, atol=1e-7, msg=f"rank {rank}: {n}"
            )
    # The averaged gradient differs from either rank's own half-batch gradient (a real check).
    half = Trainer(
        ddp_problem()[0], ddp_step, lambda gen, bs: (x[:4], y[:4]), cfg, tmp_path / "half"
    )
    half.fit()
    assert not torch.allclose(next(half.model.parameters()).grad, reference["0.weight"])
    # Rank 0 alone wrote the checkpoint, its elapsed time and the log; both ranks took the same
    # optimiser step.
    assert sorted(p.name for p in out.iterdir()) == [
        "best.pt",
        "elapsed.json",
        "grads-rank0.pt",
        "grads-rank1.pt",
        "last.pt",
        "last.rank1.pt",  # rank 1's own batch generator (for resume)
        "log.csv",
    ]
    ddp_state = torch.load(out / "last.pt", weights_only=True)["model"]
    for n, p in model.state_dict().items():
        torch.testing.assert_close(ddp_state[n], p, rtol=1e-5, atol=1e-6, msg=n)


def _batches_run(out, phase: str) -> list[dict]:
    tmp.spawn(ddp_batches_rank_main, args=(2, _free_port(), str(out), phase), nprocs=2, join=True)
    return [json.loads((out / f"{phase}-rank{r}.json").read_text()) for r in (0, 1)]


def test_a_non_finite_loss_on_one_rank_skips_the_step_on_every_rank(tmp_path):
    """Rank 1's second loss is NaN: both ranks skip that step together and finish (a rank
    skipping backward() alone paired the other's gradient exchange with its next step, and the
    run broke or hung)."""
    for rank in _batches_run(tmp_path, "nan"):
        assert rank["steps"] == 4 and rank["bad_steps"] == 1


def test_a_resumed_run_draws_each_ranks_own_batches(tmp_path):
    """Killed after the step-2 checkpoint and resumed: each rank draws the batches it drew in
    the uninterrupted run (every rank took rank 0's generator from last.pt before)."""
    full = _batches_run(tmp_path / "a", "full")
    _batches_run(tmp_path / "b", "first")
    resumed = _batches_run(tmp_path / "b", "resume")
    assert full[0]["batches"][2:] != full[1]["batches"][2:]
    for rank in (0, 1):
        assert resumed[rank]["batches"] == full[rank]["batches"][2:]


def test_a_resumed_run_resumes_every_rank_from_rank_0s_checkpoint(tmp_path):
    """Under the pipeline's torchrun, ranks other than 0 run in empty folders of their own:
    each rank looking for its own last.pt resumed rank 0 alone, the others started from step 0
    with other weights, and the run broke when rank 0 finished first. Now every rank resumes
    from rank 0's checkpoint, and they end with the same weights."""
    _batches_run(tmp_path, "first")
    resumed = _batches_run(tmp_path, "resume_private")
    assert [len(r["batches"]) for r in resumed] == [2, 2]  # steps 3 and 4 on both ranks
    assert resumed[0]["weights"] == resumed[1]["weights"]
    # rank 0 draws as the uninterrupted run did; rank 1's generator state stayed in its deleted
    # folder, so it draws a fresh stream of its own
    full = _batches_run(tmp_path / "full", "full")
    assert resumed[0]["batches"] == full[0]["batches"][2:]
