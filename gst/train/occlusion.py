"""Other people's pixels in each crop, so the image terms can ignore them.

A person's mask stops where somebody in front of them starts. Compared with that mask, a correct
render of the whole body is wrong wherever the occluder stands, and the cheapest way for the
Gaussians to agree is to fade (the demo's two runners overlap in most frames). GST's loss should
say nothing about those pixels: we do not know what is behind the occluder.

Two crops of one camera and frame are undistorted views of the same image with intrinsics
K_p and K_q, so crop q's pixels map to crop p's exactly by the similarity K_p K_q^-1; each crop's
occluder mask is the union of the other people's warped masks there.
"""

from __future__ import annotations

import torch
from kornia.geometry.transform import warp_affine

from gst.train.views import CropSet


def occluder_masks(crops: CropSet) -> torch.Tensor:
    """(N, S, S) float in [0, 1]: other people's masks of the same camera and frame in each crop."""
    n, size = len(crops), crops.crop_size
    out = torch.zeros(n, size, size)
    key = crops.frame * (len(crops.camera_names) + 1) + crops.camera
    order = torch.argsort(key, stable=True)
    _, counts = torch.unique_consecutive(key[order], return_counts=True)
    for rows in torch.split(order, counts.tolist()):
        if len(rows) < 2:
            continue
        for p in rows.tolist():
            others = rows[rows != p]
            A = crops.K[p].double()[None] @ torch.linalg.inv(crops.K[others].double())
            warped = warp_affine(
                crops.masks[others][:, None].float(),
                A[:, :2].float(),
                (size, size),
                mode="bilinear",
                padding_mode="zeros",
                align_corners=True,
            )[:, 0]
            out[p] = warped.amax(0)
    return out


def ignored_share(mask: torch.Tensor, occluders: torch.Tensor) -> torch.Tensor:
    """(..., H, W) share of each pixel `ignore_occluded` leaves unsupervised: another person's,
    not this person's own."""
    return (occluders * (1 - mask)).clamp(0, 1)


def ignore_occluded(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    occluders: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Targets that agree with the render wherever another person hides this one, so those pixels
    give the image terms no gradient (exactly zero for MSE and alpha). rgb/target (..., H, W, 3),
    alpha/mask/occluders (..., H, W). The person's own pixels always stay supervised."""
    ignore = ignored_share(mask, occluders)
    target = target * (1 - ignore[..., None]) + rgb.detach() * ignore[..., None]
    mask = mask * (1 - ignore) + alpha.detach() * ignore
    return target, mask


def supervised_psnr(
    rgb: torch.Tensor, target: torch.Tensor, ignored: torch.Tensor | None = None
) -> torch.Tensor:
    """PSNR (dB) of rgb against target (..., H, W, 3) in [0, 1] over the supervised pixels: those
    `ignored` (..., H, W; `ignore_occluded`'s share) leaves out count as much as they are
    supervised. The logged training PSNR counted them, with the render pasted in, as perfect:
    10 log10(1 / (1 - share)) dB too high (3 dB with half the pixels ignored)."""
    err = ((rgb - target) ** 2).mean(-1)
    if ignored is None:
        mse = err.mean()
    else:
        w = 1 - ignored
        mse = (err * w).sum() / w.sum().clamp_min(1e-6)
    return -10 * torch.log10(mse.clamp_min(1e-10))
