"""Picklable item functions for the scale-out tests (workers import them as
tests.scaleout_items)."""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class MarkedItem:
    """An item that writes one result file; `crash` items kill their worker the first time."""

    value: int
    out_dir: Path
    crash: str = ""  # "" | "kill" (SIGKILL own process) | "raise" (an exception)


def square_and_record(item: MarkedItem) -> int:
    """Square the value and append a line to its log, crashing the first time if asked to."""
    marker = item.out_dir / f"attempted-{item.value}"
    first_attempt = not marker.exists()
    marker.touch()
    with open(item.out_dir / f"log-{item.value}.txt", "a") as fh:  # one line per completed attempt
        if item.crash and first_attempt:
            if item.crash == "kill":
                os.kill(os.getpid(), signal.SIGKILL)
            raise RuntimeError(f"deliberate failure of item {item.value}")
        fh.write(f"{item.value}\n")
    return item.value * item.value


def always_fails(x: int) -> int:
    raise ValueError(f"bad item {x}")


def worker_pid(x: int) -> tuple[int, int]:
    return x, os.getpid()


class KillOnceDetector:
    """Supplied boxes that SIGKILL their own worker process at `kill_frame`, once (marker file)."""

    def __init__(self, csv: Path, video: str, marker: Path, kill_frame: int):
        from gst.track.detection import SuppliedBoxes

        self.inner = SuppliedBoxes.from_file(csv, video)
        self.marker, self.kill_frame = Path(marker), kill_frame

    def detect(self, image, frame_index: int):
        if frame_index == self.kill_frame and not self.marker.exists():
            self.marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.detect(image, frame_index)


COMBINED_BATCH = 8


def ddp_problem():
    """A small conv + MLP regression with a fixed combined batch (same on every rank)."""
    import torch
    from torch import nn

    torch.manual_seed(0)
    model = nn.Sequential(
        nn.Conv2d(3, 4, 3, padding=1),
        nn.ReLU(),
        nn.Flatten(),
        nn.Linear(4 * 6 * 6, 8),
        nn.Tanh(),
        nn.Linear(8, 2),
    )
    g = torch.Generator().manual_seed(1)
    x = torch.randn(COMBINED_BATCH, 3, 6, 6, generator=g)
    y = torch.randn(COMBINED_BATCH, 2, generator=g)
    return model, x, y


def ddp_step(m, batch):
    """The regression's training step: mean squared error, no logged values."""
    xb, yb = batch
    return ((m(xb) - yb) ** 2).mean(), {}


def ddp_config(batch_size: int):
    """One optimiser step with a checkpoint and a log line, the same for the ranks and the
    single-process reference."""
    from gst.train.trainer import TrainConfig

    return TrainConfig(
        steps=1,
        batch_size=batch_size,
        lr=1e-3,
        warmup_steps=0,
        grad_clip=1e9,
        ckpt_every=1,
        val_every=100,
        log_every=1,
    )


def _become_rank(rank: int, world: int, port: int) -> None:
    """This process as rank `rank` of a torchrun-like world on localhost, one torch thread."""
    import torch

    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        WORLD_SIZE=str(world),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
    )
    torch.set_num_threads(1)


def ddp_rank_main(rank: int, world: int, port: int, out_dir: str) -> None:
    """One torchrun-like rank: a Trainer step on this rank's share of the combined batch."""
    import torch

    _become_rank(rank, world, port)
    from gst.train.trainer import Trainer

    model, x, y = ddp_problem()
    share = COMBINED_BATCH // world

    def sample(gen, bs):
        return x[rank * share : (rank + 1) * share], y[rank * share : (rank + 1) * share]

    trainer = Trainer(model, ddp_step, sample, ddp_config(share), Path(out_dir))
    assert trainer.world == world and trainer.rank == rank
    trainer.fit()
    grads = {n: p.grad.detach().clone() for n, p in model.named_parameters()}
    torch.save(grads, Path(out_dir) / f"grads-rank{rank}.pt")
    torch.distributed.destroy_process_group()


def ddp_batches_rank_main(rank: int, world: int, port: int, out_dir: str, phase: str) -> None:
    """A rank that records the batches it draws (its own generator) over 4 steps of a toy
    regression. phase "full": 4 steps; "first": 2 steps (then killed, as it were); "resume":
    resumes the "first" run to 4 steps; "resume_private": the same, every rank but 0 in an
    empty folder of its own (as the pipeline runs them under torchrun); "nan": 4 steps, rank 1's
    second loss is NaN."""
    import json

    import torch
    from torch import nn

    _become_rank(rank, world, port)
    from gst.train.trainer import TrainConfig, Trainer

    drawn, calls = [], [0]

    def sample(gen, bs):
        x = torch.randint(1000, (bs,), generator=gen)
        drawn.append(x.tolist())
        return x.float()[:, None] / 1000

    def step(m, b):
        calls[0] += 1
        loss = (m(b) ** 2).mean()
        if phase == "nan" and rank == 1 and calls[0] == 2:
            loss = loss * float("nan")
        return loss, {}

    steps = 2 if phase == "first" else 4
    cfg = TrainConfig(
        steps=steps, batch_size=3, warmup_steps=0, ckpt_every=2, val_every=100, log_every=100
    )
    torch.manual_seed(0)
    folder = Path(out_dir) / ("run" if phase != "resume_private" or rank == 0 else f"run.{rank}")
    trainer = Trainer(nn.Linear(1, 1), step, sample, cfg, folder)
    if phase in ("resume", "resume_private"):
        assert trainer.resume()
    summary = trainer.fit()
    record = {
        "batches": drawn,
        "bad_steps": summary.bad_steps,
        "steps": summary.steps,
        "weights": [p.item() for p in trainer.model.parameters()],
    }
    (Path(out_dir) / f"{phase}-rank{rank}.json").write_text(json.dumps(record))
    torch.distributed.destroy_process_group()
