"""A small, exact-resume training loop: AdamW, warmup + cosine, clipping, NaN guard, DDP.

The loop knows nothing about GST: it is given a `step_fn(batch) -> (loss, metrics)`, a
`sample_fn(generator, batch_size) -> batch` and an optional `val_fn() -> metrics`. All
randomness of sampling comes from one `torch.Generator` whose state is checkpointed with the
model, optimiser and scheduler, so a run killed at any point and resumed from `last.pt`
continues with the same step, the same optimiser state and the same next batch.

Under `torchrun` (WORLD_SIZE > 1) the model is wrapped in DistributedDataParallel (gloo on CPU,
nccl on CUDA); each rank draws its own batches from a generator of its own (`rank_seed`),
rank 0 alone writes checkpoints and logs.

`TrainConfig.device` places the model (`gst.device`: auto, cpu, cuda); batches are drawn on the
CPU, from the same generator on every device, and moved to the model's device before each step.
Checkpoints hold CPU tensors, so a GPU-trained model loads anywhere.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import pickle
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from gst.atomic import atomic_torch_save, atomic_write, atomic_write_json
from gst.device import move_to, resolve_device
from gst.records import Record

log = logging.getLogger("gst.train")


@dataclass
class TrainConfig:
    steps: int = 1000
    batch_size: int = 8
    lr: float = 1e-4
    weight_decay: float = 1e-4
    warmup_steps: int = 50
    min_lr_ratio: float = 0.05
    grad_clip: float = 1.0
    val_every: int = 100
    ckpt_every: int = 50
    log_every: int = 10
    max_bad_steps: int = 20  # abort after this many skipped (non-finite) steps
    amp: bool = False  # bf16 autocast; helps on GPUs, usually not on CPU
    seed: int = 0
    device: str = "cpu"  # where the model trains: auto, cpu, cuda, cuda:N (gst.device)

    @classmethod
    def for_stage(
        cls, steps: int, batch_size: int, lr: float, device: str, amp: bool, validations: int
    ) -> TrainConfig:
        """The pipeline stages' schedule: warm-up over a tenth of the run (at most 30 steps),
        `validations` checks spread over it, a checkpoint every 25 steps."""
        return cls(
            steps=steps,
            batch_size=batch_size,
            lr=lr,
            warmup_steps=min(30, steps // 10),
            val_every=max(1, steps // validations),
            ckpt_every=25,
            log_every=5,
            device=device,
            amp=amp,
        )


class NonFiniteLossError(RuntimeError):
    pass


@dataclass(frozen=True)
class TrainRunSummary(Record):
    """What `Trainer.fit` returns: the step reached, the skipped (non-finite) steps, the best
    validation value of `best_key` (None without one) and the training seconds (resumed runs
    included)."""

    steps: int
    bad_steps: int
    best: float | None
    seconds: float


def warmup_cosine(step: int, steps: int, warmup_steps: int, min_lr_ratio: float = 0.0) -> float:
    """Learning-rate factor of `step`: linear warmup over `warmup_steps`, then a cosine decay
    to `min_lr_ratio` at `steps` (the lift pretraining's schedule too, with a ratio of 0)."""
    if step < warmup_steps:
        return (step + 1) / max(1, warmup_steps)
    progress = (step - warmup_steps) / max(1, steps - warmup_steps)
    return min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))


# devices whose AdamW has a fused kernel (one pass over each parameter instead of a dozen
# elementwise ops per tensor): on the CPU it cut the lift pretraining's step by ~9 %
FUSED_ADAMW_DEVICES = ("cpu", "cuda")


def adamw(params, lr: float, weight_decay: float) -> torch.optim.AdamW:
    """AdamW over `params` (tensors or param groups), fused where the parameters' device has the
    kernel; same update rule either way (results agree to float rounding)."""
    # a group's params may come as an iterator: read once, handed on as a list
    groups = [dict(g, params=list(g["params"])) if isinstance(g, dict) else g for g in params]
    tensors = [p for g in groups for p in (g["params"] if isinstance(g, dict) else [g])]
    fused = bool(tensors) and all(p.device.type in FUSED_ADAMW_DEVICES for p in tensors)
    return torch.optim.AdamW(groups, lr=lr, weight_decay=weight_decay, fused=fused or None)


def rank_seed(seed: int, rank: int, step: int | None = None) -> int:
    """The seed of `rank`'s batch generator (at `step`: a fresh stream drawn mid-run, when the
    rank's own was lost). Rank 0 from the start keeps `seed`, so a single process draws as it
    always has; every other (seed, rank, step) is mixed by numpy's SeedSequence, so no run's
    rank repeats another run's stream (seed + 1000 * rank gave seed 1000's rank 0 the batches
    of seed 0's rank 1)."""
    if rank == 0 and step is None:
        return seed
    key = [seed % 2**64, rank] + ([] if step is None else [step + 1])
    return int(np.random.SeedSequence(key).generate_state(1, np.uint64)[0] >> 1)


def distributed_env(device: torch.device | None = None) -> tuple[int, int]:
    """(rank, world size), initialising the process group when launched by torchrun: nccl when
    the model trains on CUDA, gloo on the CPU (also on a machine that has a GPU)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        on_cuda = device.type == "cuda" if device is not None else torch.cuda.is_available()
        dist.init_process_group("nccl" if on_cuda else "gloo")
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


# settings that do not change what a step computes: a resumed run may take other values
_BOOKKEEPING = ("val_every", "ckpt_every", "log_every", "device", "max_bad_steps")


def _changed_settings(saved: dict | None, now: dict) -> list[str]:
    """`key: saved -> now` for each training setting a resumed run changes (bookkeeping aside;
    nothing for a checkpoint that records none)."""
    if not isinstance(saved, dict):
        return []
    keys = sorted((set(saved) | set(now)) - set(_BOOKKEEPING))
    return [f"{k}: {saved.get(k)!r} -> {now.get(k)!r}" for k in keys if saved.get(k) != now.get(k)]


class Trainer:
    def __init__(
        self,
        model: nn.Module,
        step_fn: Callable[[nn.Module, Any], tuple[torch.Tensor, dict]],
        sample_fn: Callable[[torch.Generator, int], Any],
        cfg: TrainConfig,
        out_dir: Path,
        *,
        val_fn: Callable[[nn.Module], dict] | None = None,
        best_key: str | None = None,
        best_mode: str = "max",
        progress: Callable | None = None,
        checkpoint_extra: Callable[[], dict] | None = None,
        param_groups: list[dict] | None = None,
        resume_check: Callable[[dict], str | None] | None = None,
    ):
        self.cfg, self.out_dir = cfg, Path(out_dir)
        self.device = resolve_device(cfg.device)
        self.rank, self.world = distributed_env(self.device)
        # moved before the optimiser is built (param_groups keep the same Parameter objects)
        self.model = model.to(self.device)
        self.train_model = model
        if self.world > 1:
            self.train_model = nn.parallel.DistributedDataParallel(
                self.model, find_unused_parameters=True
            )
        self.step_fn, self.sample_fn, self.val_fn = step_fn, sample_fn, val_fn
        # param_groups: optimizer groups with their own "lr" (e.g. Gaussian head vs body); the
        # schedule scales every group alike.
        params = param_groups or [{"params": [p for p in model.parameters() if p.requires_grad]}]
        self.optimizer = adamw(params, cfg.lr, cfg.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer,
            lambda s: warmup_cosine(s, cfg.steps, cfg.warmup_steps, cfg.min_lr_ratio),
        )
        self.generator = torch.Generator().manual_seed(rank_seed(cfg.seed, self.rank))
        self.best_key, self.best_mode = best_key, best_mode
        self.best_value: float | None = None
        self.step = 0
        self.bad_steps = 0
        self.seconds_before = 0.0  # training time of the runs this one resumes
        self.progress = progress
        self.checkpoint_extra = checkpoint_extra or (lambda: {})
        # what a caller checks in last.pt before resuming it (returns why it cannot, or None):
        # the caller's own fields (held-out data, layout) that the weights' shapes do not show
        self.resume_check = resume_check
        self.history: list[dict] = []
        self._t0: float | None = None

    # -- checkpoints ------------------------------------------------------------------------
    @property
    def last_path(self) -> Path:
        return self.out_dir / "last.pt"

    @property
    def best_path(self) -> Path:
        return self.out_dir / "best.pt"

    @property
    def rank_state_path(self) -> Path:
        """Where a rank other than 0 keeps its own batch generator beside `last.pt`."""
        return self.out_dir / f"last.rank{self.rank}.pt"

    def state(self) -> dict:
        return {
            "step": self.step,
            "bad_steps": self.bad_steps,
            "best_value": self.best_value,
            "optimizer": move_to(self.optimizer.state_dict(), "cpu"),
            "scheduler": self.scheduler.state_dict(),
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "train_config": asdict(self.cfg),
        }

    def save(self, path: Path) -> None:
        if self.rank != 0 and path == self.last_path:
            # each rank draws its own batches: its generator must resume too (last.pt holds
            # rank 0's; every rank taking that one trained all ranks on the same batches)
            atomic_torch_save(
                {
                    "step": self.step,
                    "generator": self.generator.get_state(),
                    "torch_rng": torch.get_rng_state(),
                },
                self.rank_state_path,
            )
        if self.rank == 0:
            atomic_torch_save(
                {
                    "model": move_to(self.model.state_dict(), "cpu"),
                    "trainer": self.state(),
                    **self.checkpoint_extra(),
                },
                path,
            )
            if path == self.last_path:
                # Wall-clock time stays out of the checkpoints (they are outputs and must not
                # change from run to run); a resumed run reads it here to keep counting.
                elapsed = self.seconds_before + (
                    time.perf_counter() - self._t0 if self._t0 else 0.0
                )
                atomic_write_json(
                    self.out_dir / "elapsed.json", {"step": self.step, "seconds": elapsed}
                )

    def resume(self, path: Path | None = None) -> bool:
        """Continue from `last.pt` if it exists. Returns whether it resumed.

        Under DDP, rank 0's checkpoint decides for every rank: it is sent to the others, which
        need not see rank 0's folder (the pipeline runs them in private staging folders that
        it deletes). Each rank looking on its own resumed rank 0 alone: the others started
        again from step 0 with other weights, and the run broke or hung when rank 0 finished
        first."""
        path = path or self.last_path
        found = self.rank == 0 and path.is_file()  # (a single process is rank 0)
        ckpt = _read_resume(path) if found else None
        if self.world > 1:
            sent = [ckpt]  # (between this run's own processes: pickled in memory)
            dist.broadcast_object_list(sent, src=0, device=self._object_device())
            ckpt = sent[0]
        if ckpt is None:
            return False
        why = self.resume_check(ckpt) if self.resume_check is not None else None
        if why:
            raise ValueError(
                f"{path}: {why}, so this run cannot resume it (delete it to start afresh, or "
                "train into another folder)"
            )
        st = ckpt["trainer"]
        # checked before anything changes: a missing entry failed with a bare KeyError after
        # the weights and the optimiser were loaded
        lacking = [
            k
            for k in ("scheduler", "generator", "torch_rng", "step", "bad_steps", "best_value")
            if not isinstance(st, dict) or k not in st
        ]
        if lacking:
            raise ValueError(
                f"{path}: its trainer state lacks {', '.join(repr(k) for k in lacking)}, so "
                "this run cannot resume it (delete it to start afresh, or train into another "
                "folder)"
            )
        # checked before anything changes: torch's own check comes after the weights are loaded
        mismatch = _optimizer_mismatch(st.get("optimizer"), self.optimizer)
        if mismatch:
            raise ValueError(
                f"{path}: its optimiser state does not fit this run's optimiser ({mismatch}; the "
                "parameter groups changed, e.g. body_lr set or left out), so this run cannot "
                "resume it (delete it to start afresh, or train into another folder)"
            )
        try:  # another network's last.pt: the file named, not torch's bare size mismatch
            self.model.load_state_dict(ckpt["model"])
        except RuntimeError as exc:
            raise ValueError(
                f"{path}: a checkpoint of another network, which this run cannot resume (delete "
                f"it to start afresh, or train into another folder): {exc}"
            ) from exc
        changed = _changed_settings(st.get("train_config"), asdict(self.cfg))
        if changed:  # the pipeline starts a changed run afresh; a library caller may not mean to
            log.warning(
                "resuming %s, written with other settings: %s (a new folder starts afresh)",
                path, ", ".join(changed),
            )  # fmt: skip
        try:  # what the check above does not see (torch's own checks), the file named
            self.optimizer.load_state_dict(st["optimizer"])
        except (KeyError, RuntimeError, TypeError, ValueError) as exc:
            raise ValueError(
                f"{path}: its optimiser state does not fit this run's optimiser ({exc}); delete "
                "it to start afresh, or train into another folder"
            ) from exc
        self.scheduler.load_state_dict(st["scheduler"])
        self.generator.set_state(st["generator"])
        torch.set_rng_state(st["torch_rng"])
        self.step, self.bad_steps, self.best_value = st["step"], st["bad_steps"], st["best_value"]
        if self.rank != 0:
            self._resume_rank_state()
        self.seconds_before = self._elapsed_at(self.step)
        self._forget_logged_after(self.step)
        log.info("resumed from %s at step %d", path, self.step)
        return True

    def _object_device(self) -> torch.device:
        """Where `broadcast_object_list` stages its bytes: NCCL needs this rank's GPU."""
        return self.device if dist.get_backend() == "nccl" else torch.device("cpu")

    def _resume_rank_state(self) -> None:
        """This rank's own generator at the checkpoint's step; without it (killed between the
        two writes, or a checkpoint of another world size) a fresh stream of its own."""
        path = self.rank_state_path
        try:
            own = torch.load(path, weights_only=True) if path.is_file() else None
        except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
            # a file cut short or damaged (a disk filled): as if missing, said, not a traceback
            log.warning("rank %d: cannot read %s (%s)", self.rank, path, exc)
            own = None
        if not isinstance(own, dict):
            own = None
        if own is not None and own.get("step") == self.step:
            self.generator.set_state(own["generator"])
            torch.set_rng_state(own["torch_rng"])
            return
        log.warning(
            "rank %d: no batch generator of its own at step %d (%s): drawing a fresh stream",
            self.rank, self.step, path,
        )  # fmt: skip
        self.generator.manual_seed(rank_seed(self.cfg.seed, self.rank, self.step))

    def _on_every_rank(self, ok: bool) -> bool:
        """Whether `ok` holds on every rank. Ranks must agree to skip a step: backward() is
        where DDP exchanges gradients, so one rank skipping it alone pairs the others'
        exchange with its next step."""
        if self.world == 1:
            return ok
        flag = torch.tensor([1.0 if ok else 0.0], device=self.device)
        dist.all_reduce(flag, op=dist.ReduceOp.MIN)
        return bool(flag.item() > 0)

    def _elapsed_at(self, step: int) -> float:
        try:
            rec = json.loads((self.out_dir / "elapsed.json").read_text())
        except (OSError, ValueError):
            return 0.0
        return float(rec.get("seconds", 0.0)) if rec.get("step") == step else 0.0

    def _forget_logged_after(self, step: int) -> None:
        """A killed run logged steps after its last checkpoint; the resumed run computes them
        again, so those rows go (the log then holds every step once, in order)."""
        path = self.out_dir / "log.csv"
        if self.rank != 0 or not path.is_file():
            return
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            fields, rows = reader.fieldnames or [], list(reader)
        kept = [r for r in rows if int(float(r.get("step") or 0)) <= step]
        if len(kept) == len(rows):
            return

        def write(tmp) -> None:
            with open(tmp, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=fields)
                writer.writeheader()
                writer.writerows(kept)

        atomic_write(path, write)

    # -- loop -------------------------------------------------------------------------------
    def _log_row(self, row: dict) -> None:
        self.history.append(row)
        if self.rank != 0:
            return
        path = self.out_dir / "log.csv"
        fields: list[str] = []
        if path.exists():
            with open(path, newline="") as f:
                fields = next(csv.reader(f), [])
        if fields and set(row) <= set(fields):
            with open(path, "a", newline="") as f:
                csv.DictWriter(f, fieldnames=fields).writerow(row)
            return
        # A column the file lacks (the first validation, the first skipped step): rewrite it with
        # the union of columns. Appending under the old header silently dropped those values.
        old_rows: list[dict] = []
        if path.exists():
            with open(path, newline="") as f:
                old_rows = list(csv.DictReader(f))
        fields = fields + sorted(set(row) - set(fields))

        def write(tmp: str) -> None:
            with open(tmp, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=fields)
                writer.writeheader()
                writer.writerows(old_rows + [row])

        atomic_write(path, write)

    def _is_better(self, value: float) -> bool:
        """Whether a validation `value` beats the best so far. A non-finite one never does, and
        a non-finite best (a checkpoint of older code) is none: a NaN first value was kept as
        the best, every comparison with it false, and best.pt froze on that model."""
        if not math.isfinite(value):
            log.warning(
                "validation %s is %s at step %d: not a best", self.best_key, value, self.step
            )
            return False
        if self.best_value is None or not math.isfinite(self.best_value):
            return True
        return value > self.best_value if self.best_mode == "max" else value < self.best_value

    def validate(self) -> dict:
        if self.val_fn is None:
            return {}
        self.model.eval()
        with torch.no_grad():
            metrics = self.val_fn(self.model)
        self.model.train()
        return metrics

    def train_step(self) -> dict:
        batch = move_to(self.sample_fn(self.generator, self.cfg.batch_size), self.device)
        self.optimizer.zero_grad(set_to_none=True)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.cfg.amp):
            loss, metrics = self.step_fn(self.train_model, batch)
        finite = self._on_every_rank(bool(torch.isfinite(loss)))
        if finite:
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
            finite = bool(torch.isfinite(grad_norm))
        if not finite:
            # NaN guard: drop this step entirely (no optimiser update), count it, maybe abort.
            self.optimizer.zero_grad(set_to_none=True)
            self.bad_steps += 1
            log.warning(
                "step %d: non-finite loss or gradient, skipped (%d so far)",
                self.step,
                self.bad_steps,
            )
            if self.bad_steps >= self.cfg.max_bad_steps:
                raise NonFiniteLossError(
                    f"{self.bad_steps} non-finite steps (limit {self.cfg.max_bad_steps}); "
                    "lower the learning rate or check the inputs"
                )
            metrics = {**metrics, "skipped": 1}
        else:
            self.optimizer.step()
            metrics = {**metrics, "grad_norm": float(grad_norm)}
        # the rate this step used (after `scheduler.step()`, `get_last_lr` is the next step's)
        metrics = {**metrics, "lr": self.optimizer.param_groups[0]["lr"]}
        self.scheduler.step()
        return {"loss": float(loss.detach()), **{k: float(v) for k, v in metrics.items()}}

    def fit(self) -> TrainRunSummary:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.model.train()
        if self.rank == 0:
            log.info(
                "training on %s (device: %s%s)",
                torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else "cpu",
                self.cfg.device,
                ", bf16 autocast" if self.cfg.amp else "",
            )
        t0 = self._t0 = time.perf_counter()
        steps = range(self.step, self.cfg.steps)
        iterator = (
            self.progress(steps, description="training", total=len(steps))
            if self.progress
            else steps
        )
        last_val: dict = {}
        for _ in iterator:
            row = self.train_step()
            self.step += 1
            elapsed = self.seconds_before + time.perf_counter() - t0
            row.update(step=self.step, seconds=elapsed)
            if self.step % self.cfg.val_every == 0 or self.step == self.cfg.steps:
                last_val = self.validate()
                row.update({f"val_{k}": v for k, v in last_val.items()})
                key = self.best_key
                if key and f"val_{key}" in row and self._is_better(row[f"val_{key}"]):
                    self.best_value = row[f"val_{key}"]
                    self.save(self.best_path)
            if self.step % self.cfg.log_every == 0 or self.step == self.cfg.steps or last_val:
                self._log_row(row)
            if self.step % self.cfg.ckpt_every == 0 or self.step == self.cfg.steps:
                self.save(self.last_path)
            last_val = {}
        if self.best_key is None or not self.best_path.exists():
            self.save(self.best_path)
        return TrainRunSummary(
            steps=self.step,
            bad_steps=self.bad_steps,
            best=self.best_value,
            seconds=self.seconds_before + time.perf_counter() - t0,
        )


def _optimizer_mismatch(saved, optimizer: torch.optim.Optimizer) -> str | None:
    """How a saved optimiser state's parameter groups differ from `optimizer`'s (their number,
    or the parameters in each), or None when they match: what `Optimizer.load_state_dict`
    refuses, but only after the model's weights were loaded."""
    groups = saved.get("param_groups") if isinstance(saved, dict) else None
    if not isinstance(groups, list) or not all(
        isinstance(g, dict) and isinstance(g.get("params"), list) for g in groups
    ):
        return "no parameter groups in the file"
    had = [len(g["params"]) for g in groups]
    has = [len(g["params"]) for g in optimizer.param_groups]
    if had != has:
        return f"parameters per group: {had} in the file, {has} in this run"
    return None


def _read_resume(path: Path) -> dict:
    """A training run's own `last.pt`, or a ValueError naming it (a copied or foreign file
    failed with a bare RuntimeError or KeyError 101)."""
    from gst.model.checkpoint import load_refusal

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated, not a torch file, pickled objects
        raise ValueError(
            f"{path}: cannot resume from it ({load_refusal(exc)}); delete it to start afresh"
        ) from None
    if not isinstance(ckpt, dict) or not {"model", "trainer"} <= set(ckpt):
        raise ValueError(
            f"{path}: not a training run's checkpoint (no model and trainer state); delete it to "
            "start afresh"
        )
    return ckpt
