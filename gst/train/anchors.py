"""Where each person is, from the calibrated masks alone: a label-free anchor for the body.

The image terms only pull on Gaussians that overlap the person in the target view. When the
start is far off (our CPU pretraining puts the pelvis 0.3-0.6 m from the truth on the demo), the
body lands beside the person in the other views, no Gaussian overlaps the mask, and fading to
transparent is the cheapest way to lower the loss. HMR2's start avoids this in the paper; we add
a geometric cue that needs no 3D labels: the mask centroids of one person in the training views
are triangulated (DLT with each crop's own K [R | t]) and the predicted body's centre is pulled
towards that point when it is more than a margin away (`anchor_term`).
"""

from __future__ import annotations

import numpy as np
import torch

from calibration.triangulate import dlt_points
from gst.train.views import CropSet


def mask_centroids(
    masks: torch.Tensor, min_pixels: float = 50.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, S, S) masks -> (N, 2) centroids in crop pixels (pixel centres at integers) and (N,)
    ok."""
    s = masks.shape[-1]
    grid = torch.arange(s, dtype=torch.float64)
    w = masks.double()
    total = w.sum((1, 2))
    u = (w.sum(1) * grid).sum(1) / total.clamp_min(1e-9)
    v = (w.sum(2) * grid).sum(1) / total.clamp_min(1e-9)
    return torch.stack([u, v], -1), total >= min_pixels


def mask_centre_anchors(
    crops: CropSet, cameras: set[int] | None = None, max_error: float = 0.08
) -> torch.Tensor:
    """(N, 3) world point per crop: its person's triangulated mask centroid over the crops of
    `cameras` (default all) in the same frame; NaN where fewer than 2 views have a mask or the
    centroids disagree (mean reprojection error above `max_error` of the crop size)."""
    out = torch.full((len(crops), 3), float("nan"), dtype=torch.float64)
    uv, ok = mask_centroids(crops.masks)
    P = (crops.K.double() @ torch.cat([crops.R.double(), crops.t.double()[:, :, None]], 2)).numpy()
    for g in crops.groups(cameras=cameras, min_views=2):
        use = g[ok[g]]
        if len(use) < 2:
            continue
        Ps, pts = P[use.numpy()], uv[use].numpy()
        X = dlt_points(Ps, pts[:, None, :])[0]
        proj = Ps @ np.append(X, 1.0)
        if np.any(proj[:, 2] <= 0):
            continue
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - pts, axis=1).mean() / crops.crop_size
        if err <= max_error:
            out[g] = torch.as_tensor(X)
    return out.float()


def anchor_term(centres: torch.Tensor, anchors: torch.Tensor, margin: float = 0.1) -> torch.Tensor:
    """Mean over rows with an anchor of max(0, |centre - anchor| - margin), metres; 0 if none.
    The margin leaves the fine placement to the image terms (a mask centroid is not exactly the
    body's centre)."""
    valid = torch.isfinite(anchors).all(-1)
    if not bool(valid.any()):
        return centres.sum() * 0
    dist = (centres[valid] - anchors[valid].to(centres)).norm(dim=-1)
    return (dist - margin).clamp_min(0).mean()
