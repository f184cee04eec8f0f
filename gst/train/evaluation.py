"""Validation used during and after training: pose error against truth, novel-view quality.

- Pose: MPJPE (pelvis-aligned) and PA-MPJPE, in millimetres, on crops with truth, comparing the
  predicted joints taken to the world through the input camera with the true world joints.
- Novel view: the input is a crop from a training camera; the Gaussians are rendered into the
  same person's crop in a held-out camera and compared (PSNR, SSIM on the person composited on
  black, and silhouette IoU against the mask).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch

from gst.device import model_device, move_to
from gst.metrics.image import psnr, silhouette_iou, ssim
from gst.metrics.pose import mpjpe, pa_mpjpe
from gst.train.steps import GSTTask, predict
from gst.train.views import CropSet, MultiViewBatch, target_views


@dataclass(frozen=True)
class PoseMetrics:
    """MPJPE (pelvis-aligned) and PA-MPJPE in mm, means over the crops scored."""

    mpjpe_mm: float
    pa_mpjpe_mm: float

    def to_dict(self) -> dict[str, float]:
        """The metrics by name (validation rows, log.csv columns, summary.json)."""
        return asdict(self)


@dataclass(frozen=True)
class ViewMetrics:
    """Novel-view PSNR (dB), SSIM and silhouette IoU, means over the pairs scored; `images`:
    (input, rendered, target) batches when asked for (never serialised)."""

    psnr: float
    ssim: float
    silhouette_iou: float
    images: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = field(
        default=None, repr=False, compare=False
    )

    def to_dict(self) -> dict[str, float]:
        """The metrics by name, without the images."""
        return {"psnr": self.psnr, "ssim": self.ssim, "silhouette_iou": self.silhouette_iou}


@torch.no_grad()
def pose_metrics(
    model, task: GSTTask, crops: CropSet, rows: torch.Tensor, batch_size: int = 32
) -> PoseMetrics | None:
    """MPJPE and PA-MPJPE (mm) over `rows` (crops that have truth joints_world); None when
    `rows` is empty."""
    if len(rows) == 0:
        return None
    errs, pa = [], []
    for s in range(0, len(rows), batch_size):
        r = rows[s : s + batch_size]
        pred = predict(
            model, task, crops.images[r], crops.K[r], crops.R[r], crops.t[r],
            with_gaussians=False, landmarks=crop_landmarks(crops, r),
        )  # fmt: skip
        gt = crops.truth["joints_world"][r].to(pred.joints_world)
        errs.append(mpjpe(pred.joints_world, gt, root=0))
        pa.append(pa_mpjpe(pred.joints_world, gt))
    return PoseMetrics(
        mpjpe_mm=1000 * float(torch.cat(errs).mean()),
        pa_mpjpe_mm=1000 * float(torch.cat(pa).mean()),
    )


@dataclass
class ViewPairs:
    """Fixed (input crop, target crop) rows: each target is another view of its input's person
    and frame (`novel_view_pairs` here, `gst.eval.evaluator.view_pairs` for the evaluation)."""

    inputs: torch.Tensor  # (P,)
    targets: torch.Tensor  # (P,)


def novel_view_pairs(
    crops: CropSet,
    heldout: set[int],
    max_pairs: int = 64,
    seed: int = 0,
    frames: tuple[int, int] | None = None,
) -> ViewPairs:
    """(training-camera input, held-out-camera target) pairs of one (frame, person), within
    `frames` [lo, hi) when given. With several held-out views of a group the target is drawn
    among them (every held-out camera is scored); with one it is that one."""
    gen = torch.Generator().manual_seed(seed)
    inputs, targets = [], []
    for g in crops.groups(min_views=2):
        if frames is not None and not frames[0] <= int(crops.frame[g[0]]) < frames[1]:
            continue
        held = [int(i) for i in g if int(crops.camera[i]) in heldout]
        train = [int(i) for i in g if int(crops.camera[i]) not in heldout]
        if held and train:
            inputs.append(train[int(torch.randint(len(train), (1,), generator=gen))])
            # one held-out view: no draw, so the generator's sequence (and the pairs) are those
            # of the single held-out camera the defaults have
            pick = 0 if len(held) == 1 else int(torch.randint(len(held), (1,), generator=gen))
            targets.append(held[pick])
    order = torch.randperm(len(inputs), generator=gen)[:max_pairs]
    return ViewPairs(
        torch.tensor(inputs, dtype=torch.long)[order],
        torch.tensor(targets, dtype=torch.long)[order],
    )


def crop_landmarks(crops: CropSet, rows: torch.Tensor) -> torch.Tensor | None:
    """The crops' landmarks of `rows` (None when the crop set has none)."""
    return None if crops.landmarks is None else crops.landmarks[rows]


def _batch(crops: CropSet, inp: torch.Tensor, tgt: torch.Tensor, size: int) -> MultiViewBatch:
    view, K, images, masks = target_views(crops, tgt[:, None], size)
    return MultiViewBatch(
        inp,
        tgt[:, None],
        crops.images[inp],
        crops.K[inp],
        crops.R[inp],
        crops.t[inp],
        images,
        masks,
        K,
        view,
        torch.zeros(len(inp), 1, 3),
        input_landmarks=crop_landmarks(crops, inp),
    )


@torch.no_grad()
def novel_view_metrics(
    model,
    task: GSTTask,
    crops: CropSet,
    pairs: ViewPairs,
    size: int,
    batch_size: int = 16,
    return_images: bool = False,
) -> ViewMetrics | None:
    """PSNR/SSIM of the person (composited on black) and silhouette IoU in held-out views;
    None without pairs. `return_images`: the metrics keep the compared images."""
    from gst.train.steps import render_predictions

    if len(pairs.inputs) == 0:
        return None
    ps, ss, ious, images = [], [], [], []
    for s in range(0, len(pairs.inputs), batch_size):
        b = _batch(crops, pairs.inputs[s : s + batch_size], pairs.targets[s : s + batch_size], size)
        b = move_to(b, model_device(model))
        pred = predict(
            model, task, b.input_images, b.K_in, b.R_in, b.t_in, with_gaussians=True,
            landmarks=b.input_landmarks,
        )  # fmt: skip
        out = render_predictions(pred, b, size)
        rgb = out.rgb[:, 0].permute(0, 3, 1, 2).clamp(0, 1)
        target = (b.target_images[:, 0] * b.target_masks[:, 0, ..., None]).permute(0, 3, 1, 2)
        ps.append(psnr(rgb, target))
        ss.append(ssim(rgb, target))
        ious.append(silhouette_iou(out.alpha[:, 0], b.target_masks[:, 0]))
        if return_images:
            images.append((b.input_images, rgb, target))
    return ViewMetrics(
        psnr=float(torch.cat(ps).mean()),
        ssim=float(torch.cat(ss).mean()),
        silhouette_iou=float(torch.cat(ious).mean()),
        images=images if return_images else None,
    )
