"""DDP under the Trainer: 2 CPU processes (gloo) give the single-process gradients of the
combined batch, and only rank 0 writes checkpoints and logs."""

from __future__ import annotations

import socket

import torch
import torch.multiprocessing as tmp

from gst.train.trainer import Trainer
from tests.scaleout_items import (
    COMBINED_BATCH,
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
        "log.csv",
    ]
    ddp_state = torch.load(out / "last.pt", weights_only=True)["model"]
    for n, p in model.state_dict().items():
        torch.testing.assert_close(ddp_state[n], p, rtol=1e-5, atol=1e-6, msg=n)
