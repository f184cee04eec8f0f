"""Overfit one multi-view sample: the capacity check of the Gaussian head, rasteriser and losses.

The paper reports 41 dB when GST overfits a single multi-view sample. We reproduce the check on
one (frame, person) of a synthetic scene: a short supervised warm start puts the body where the
truth says (the paper starts from HMR2, whose poses are already close), then the multi-view
objective alone (MSE + LPIPS + alpha + tightness) fits the Gaussians. PSNR is measured on the
training views: every view in turn is the input and all views are rendered, the person
composited on black on both sides.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import torch

from gst.metrics.image import psnr
from gst.train.recipe import gaussian_parameter_groups, supervised_batch
from gst.train.steps import (
    GSTTask,
    multiview_step,
    predict,
    render_predictions,
    supervised_step,
)
from gst.train.views import CropSet, sample_multiview


@dataclass
class OverfitResult:
    psnr: float  # final mean PSNR (dB) over all (input view, rendered view) pairs
    psnr_per_input: list[float]
    warm_mpjpe_mm: float | None  # root-relative error at the end of the warm start
    seconds: float
    history: list[dict] = field(default_factory=list)  # {"step", "seconds", "psnr"}


@torch.no_grad()
def training_view_psnr(
    model, task: GSTTask, crops: CropSet, group: torch.Tensor, size: int
) -> list[float]:
    """Mean PSNR of the renders into all views of `group`, once per input view."""
    was_training = model.training
    model.eval()
    base = sample_multiview(crops, [group], torch.Generator().manual_seed(0), 1, len(group), size)
    order = torch.argsort(base.target_index[0])  # targets in group order
    base = dataclasses.replace(
        base,
        target_index=base.target_index[:, order],
        target_images=base.target_images[:, order],
        target_masks=base.target_masks[:, order],
        K_target=base.K_target[:, order],
        viewmats=base.viewmats[:, order],
        backgrounds=torch.zeros_like(base.backgrounds),
    )
    target = (base.target_images * base.target_masks[..., None])[0].permute(0, 3, 1, 2)
    scores = []
    for i in group.sort().values:
        i = i.view(1)
        pred = predict(model, task, crops.images[i], crops.K[i], crops.R[i], crops.t[i])
        rgb = render_predictions(pred, base, size).rgb[0].permute(0, 3, 1, 2).clamp(0, 1)
        scores.append(float(psnr(rgb, target).mean()))
    model.train(was_training)
    return scores


def overfit_sample(
    model,
    task: GSTTask,
    crops: CropSet,
    group: torch.Tensor,
    *,
    warm_steps: int = 100,
    steps: int = 300,
    lr: float = 1e-3,
    body_lr: float = 1e-5,
    warm_lr: float = 1e-3,
    render_size: int = 64,
    num_targets: int | None = None,
    eval_every: int = 50,
    seed: int = 0,
    progress=None,
) -> OverfitResult:
    """Warm start on the group's truth (skipped without truth or with warm_steps=0), then
    `steps` multi-view steps on this one group. Trains `model` in place."""
    t0 = time.perf_counter()
    model.train()
    warm_mpjpe = None
    if warm_steps and "joints_cam" in crops.truth:
        supervision, task.supervision = task.supervision, "3d"
        opt = torch.optim.Adam(model.parameters(), lr=warm_lr)
        batch = supervised_batch(crops, group)
        for _ in range(warm_steps):
            loss, parts = supervised_step(model, batch, task)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        task.supervision = supervision
        warm_mpjpe = float(parts["mpjpe_mm"])
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(gaussian_parameter_groups(model, lr, body_lr))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / max(1, steps)))
    )
    history = []
    targets = num_targets or len(group)
    it = (
        range(steps)
        if progress is None
        else progress(range(steps), description="overfit", total=steps)
    )
    for step in it:
        batch = sample_multiview(crops, [group], gen, 1, targets, render_size)
        loss, _ = multiview_step(model, batch, task)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if eval_every and (step + 1) % eval_every == 0 and step + 1 < steps:
            history.append(
                {
                    "step": step + 1,
                    "seconds": time.perf_counter() - t0,
                    "psnr": sum(s := training_view_psnr(model, task, crops, group, render_size))
                    / len(s),
                }
            )
    final = training_view_psnr(model, task, crops, group, render_size)
    history.append(
        {"step": steps, "seconds": time.perf_counter() - t0, "psnr": sum(final) / len(final)}
    )
    return OverfitResult(
        psnr=sum(final) / len(final),
        psnr_per_input=final,
        warm_mpjpe_mm=warm_mpjpe,
        seconds=time.perf_counter() - t0,
        history=history,
    )
