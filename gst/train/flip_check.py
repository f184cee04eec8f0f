"""Training the per-scene flip check (gst.model.flip_check) on the crops the rig labels.

Each training crop whose hips and shoulders the rig's fused body shows either on their own sides
or both crossed (gst.metrics.flips.landmark_sides) is one example: its landmarks put right (the
crossed ones un-mirrored) must score below 0, which by the score's antisymmetry is the same as
their mirror scoring above 0. The same crop flipped horizontally, with its landmarks mirrored
and relabelled, is a second valid body. The last `validation` share of the training frames is
kept out of the gradient: it stops training when its loss stops falling (the check overfits a
scene's few hundred crops within a few hundred steps) and sets the temperature that turns scores
into log-odds. No held-out camera or frame is ever seen: the caller passes training rows only.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.metrics.flips import unmirror
from gst.model.flip_check import FlipCheck, FlipCheckNet, check_input

log = logging.getLogger("gst.train")


class FlipCheckSettings(BaseModel):
    """How `train` fits the flip check (`train.flip_check` in pipeline.yaml)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    max_steps: int = Field(600, ge=1)
    validate_every: int = Field(25, ge=1)  # steps
    # validations without a better validation loss before stopping, after `min_steps`
    patience: int = Field(4, ge=1)
    min_steps: int = Field(100, ge=0)
    batch_size: int = Field(64, ge=2)
    lr: float = Field(2e-3, gt=0)
    width: int = Field(16, ge=4)  # channels of the first layer (x2, x4, x4 after)
    validation: float = Field(0.25, gt=0, lt=1)  # last share of the training frames
    min_crops: int = Field(60, ge=2)  # fewer labelled training crops: no check
    seed: int = 0


@dataclass(frozen=True)
class FlipCheckReport:
    """What training the check saw and gave (written into the train summary)."""

    labelled_crops: int
    mirrored_crops: int
    validation_crops: int
    validation_mirrored: int
    steps: int
    best_step: int
    validation_loss: float
    temperature: float
    prior: float
    # on the validation crops as BlazePose read them: mirrored ones the check calls mirrored,
    # and unmirrored ones it would wrongly exchange
    validation_found: int
    validation_false: int
    seconds: float

    def to_dict(self) -> dict:
        return asdict(self)


def _hflip(images: torch.Tensor, landmarks: torch.Tensor):
    """Crops flipped horizontally, with their landmarks mirrored and relabelled: a valid body."""
    lm = landmarks.clone()
    lm[..., 0] = (images.shape[2] - 1) - lm[..., 0]
    return images.flip(2), lm[:, list(BLAZEPOSE_MIRROR)]


def _jitter(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    gain = 0.75 + 0.5 * torch.rand(len(x), 1, 1, 1, generator=gen)
    x = torch.cat([x[:, :3] * gain, x[:, 3:]], 1)
    dy, dx = (int(v) for v in torch.randint(-3, 4, (2,), generator=gen))
    return torch.roll(x, (dy, dx), (2, 3))


def _loss(net: FlipCheckNet, x: torch.Tensor) -> torch.Tensor:
    return F.softplus(net.score(x)).mean()  # the put-right landmarks: score below 0


def _fit_temperature(scores: np.ndarray) -> float:
    """The temperature that minimises the validation loss of put-right crops' scores (a grid
    from 0.5 to 16: with a perfectly separated validation the smallest, with errors larger)."""
    grid = np.geomspace(0.5, 16.0, 41)
    losses = [np.logaddexp(0.0, scores / t).mean() for t in grid]
    return float(grid[int(np.argmin(losses))])


def train_flip_check(
    images: torch.Tensor,
    landmarks: torch.Tensor,
    sides: np.ndarray,
    frames: np.ndarray,
    settings: FlipCheckSettings,
) -> tuple[FlipCheck | None, FlipCheckReport | None]:
    """Fit the check on the crops (N, S, S, 3) uint8 with their landmarks (N, 33, 3) as read,
    `sides` (N,) from gst.metrics.flips.landmark_sides against the rig's bodies (0: unlabelled;
    every labelled row must be a training row) and their `frames` (N,). Returns (None, None)
    with fewer than `settings.min_crops` labelled crops."""
    rows = np.flatnonzero(np.asarray(sides) != 0)
    if len(rows) < settings.min_crops:
        log.info(
            "flip check: %d labelled training crops (< %d): not trained",
            len(rows),
            settings.min_crops,
        )
        return None, None
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(settings.seed)
    torch.manual_seed(settings.seed)
    mirrored = np.asarray(sides)[rows] < 0
    read = torch.as_tensor(landmarks)[rows].float()
    put_right = unmirror(read, mirrored)
    imgs = torch.as_tensor(images)[rows]
    f = np.asarray(frames)[rows]
    distinct = np.unique(f)
    cut = distinct[min(len(distinct) - 1, int(np.floor(len(distinct) * (1 - settings.validation))))]
    val = f >= cut
    tr = ~val
    flipped_imgs, flipped_lms = _hflip(imgs[tr], put_right[tr])
    x_train = torch.cat(
        [check_input(imgs[tr], put_right[tr]), check_input(flipped_imgs, flipped_lms)]
    )
    x_val = check_input(imgs[val], put_right[val])
    net = FlipCheckNet(settings.width)
    opt = torch.optim.AdamW(net.parameters(), settings.lr, weight_decay=1e-3)
    best = (float("inf"), 0, None)
    step = 0
    order = torch.zeros(0, dtype=torch.long)
    while step < settings.max_steps:
        if len(order) < settings.batch_size:  # a new shuffled pass over the examples
            order = torch.randperm(len(x_train), generator=gen)
        batch, order = order[: settings.batch_size], order[settings.batch_size :]
        net.train()
        loss = _loss(net, _jitter(x_train[batch], gen))
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % settings.validate_every and step < settings.max_steps:
            continue
        net.eval()
        with torch.no_grad():
            val_loss = float(_loss(net, x_val)) if len(x_val) else 0.0
        log.debug("flip check: step %d, validation loss %.4f", step, val_loss)
        if val_loss < best[0]:
            best = (val_loss, step, {k: v.clone() for k, v in net.state_dict().items()})
        elif (
            step >= settings.min_steps
            and step - best[1] >= settings.patience * settings.validate_every
        ):
            break
    net.load_state_dict(best[2])
    net.eval()
    with torch.no_grad():
        val_scores = net.score(x_val).double().numpy() if len(x_val) else np.zeros(0)
    temperature = _fit_temperature(val_scores) if len(val_scores) else 1.0
    prior = (mirrored.sum() + 0.5) / (len(rows) + 1.0)  # the training flip rate, smoothed
    check = FlipCheck(net, temperature, float(np.log(prior / (1 - prior))))
    called = check.mirrored(imgs[val], read[val])
    report = FlipCheckReport(
        labelled_crops=len(rows),
        mirrored_crops=int(mirrored.sum()),
        validation_crops=int(val.sum()),
        validation_mirrored=int(mirrored[val].sum()),
        steps=step,
        best_step=best[1],
        validation_loss=best[0],
        temperature=temperature,
        prior=float(prior),
        validation_found=int((called & mirrored[val]).sum()),
        validation_false=int((called & ~mirrored[val]).sum()),
        seconds=time.perf_counter() - t0,
    )
    log.info(
        "flip check: %d labelled training crops (%d mirrored), best step %d of %d; on the %d "
        "validation crops it finds %d of %d mirrored and would wrongly exchange %d (%.0f s)",
        report.labelled_crops, report.mirrored_crops, report.best_step, report.steps,
        report.validation_crops, report.validation_found, report.validation_mirrored,
        report.validation_false, report.seconds,
    )  # fmt: skip
    return check, report
