"""3D pose metrics: MPJPE, PA-MPJPE (similarity Procrustes) and per-vertex error.

Units: every function returns distances in the unit of its inputs. The pipeline works in metres,
so results are metres; papers (and the GST paper's tables) report millimetres, i.e. x 1000.
Inputs are (B, N, 3) tensors: B poses of N joints or vertices. An optional `valid` (B, N) mask
(bool or 0/1 weights) drops joints without truth, e.g. low-confidence Panoptic joints.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

__all__ = [
    "Similarity",
    "mpjpe",
    "pa_mpjpe",
    "procrustes_align",
    "similarity_procrustes",
    "vertex_error",
]


def _check(
    pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None, fn: str
) -> torch.Tensor:
    if pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"{fn}: pred has shape {tuple(pred.shape)}, expected (B, N, 3)")
    if pred.shape != gt.shape:
        raise ValueError(
            f"{fn}: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must have the same shape"
        )
    if valid is None:
        return torch.ones(pred.shape[:2], dtype=pred.dtype, device=pred.device)
    if valid.shape != pred.shape[:2]:
        raise ValueError(
            f"{fn}: valid has shape {tuple(valid.shape)}, expected {tuple(pred.shape[:2])}"
        )
    return valid.to(pred.dtype)


def _zero_invalid(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """`x` with the points `w` leaves out set to 0: a weight of 0 does not cancel a NaN (NaN x 0
    is NaN), and points without truth are often NaN."""
    return torch.where(w[..., None] > 0, x, torch.zeros((), dtype=x.dtype, device=x.device))


def _mean_error(pred: torch.Tensor, gt: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted mean Euclidean distance per sample; NaN where no point is valid."""
    return ((pred - gt).norm(dim=-1) * w).sum(-1) / w.sum(-1)


def _root(x: torch.Tensor, root: int | Sequence[int]) -> torch.Tensor:
    idx = [root] if isinstance(root, int) else list(root)
    if not idx or any(not -x.shape[1] <= i < x.shape[1] for i in idx):
        raise ValueError(
            f"root {root!r} is not a joint index (or non-empty list of them) for {x.shape[1]} "
            "joints"
        )
    return x[:, idx].mean(dim=1, keepdim=True)


def mpjpe(
    pred: torch.Tensor,
    gt: torch.Tensor,
    root: int | Sequence[int] | None = None,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean per-joint position error per sample, (B,), in the inputs' unit (metres here).

    `root`: a joint index, or several whose mean is the root (e.g. both hips): each pose is
    translated so its own root sits at the origin before comparing (root-aligned MPJPE). The
    root places the pose whether or not `valid` scores it, so it must have truth: a NaN root
    gives NaN, and a placeholder (zeros where a dataset has no joint) a wrong number.
    """
    w = _check(pred, gt, valid, "mpjpe")
    if root is not None:  # the root from the poses as given (valid says which joints count)
        pred, gt = pred - _root(pred, root), gt - _root(gt, root)
    return _mean_error(_zero_invalid(pred, w), _zero_invalid(gt, w), w)


@dataclass
class Similarity:
    """x -> scale * x @ rotation.T + translation, batched.

    scale (B,), rotation (B, 3, 3), translation (B, 3).
    """

    scale: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return (
            self.scale[:, None, None] * x @ self.rotation.transpose(1, 2)
            + self.translation[:, None, :]
        ).to(x.dtype)


def similarity_procrustes(
    source: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None
) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping `source` onto `target`, both (B, N, 3).

    Rotations are proper (det +1): a mirrored prediction is not excused. Computed in float64
    with a batched SVD. Degenerate inputs (all valid source points coincide) give scale 0; a
    sample with a NaN or Inf valid point gives a NaN similarity.
    """
    w = _check(source, target, valid, "similarity_procrustes").double()
    x, y = _zero_invalid(source.double(), w), _zero_invalid(target.double(), w)
    # one non-finite sample failed the batched SVD of the whole batch (LinAlgError): solve it on
    # zeros and give it NaN, as mpjpe gives that sample NaN
    bad = ~(torch.isfinite(x).all(-1) & torch.isfinite(y).all(-1)).all(-1)  # (B,)
    x = torch.where(bad[:, None, None], torch.zeros_like(x), x)
    y = torch.where(bad[:, None, None], torch.zeros_like(y), y)
    wsum = w.sum(-1, keepdim=True).clamp_min(1e-300)[..., None]  # (B, 1, 1)
    mu_x = (w[..., None] * x).sum(1, keepdim=True) / wsum
    mu_y = (w[..., None] * y).sum(1, keepdim=True) / wsum
    xc, yc = x - mu_x, y - mu_y
    cov = (yc * w[..., None]).transpose(1, 2) @ xc / wsum  # (B, 3, 3) target x source
    u, s, vh = torch.linalg.svd(cov)
    sign = torch.sign(torch.linalg.det(u @ vh))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    d = torch.ones_like(s)
    d[:, 2] = sign
    rotation = u @ torch.diag_embed(d) @ vh
    var_x = ((xc**2).sum(-1) * w).sum(-1) / wsum[:, 0, 0]
    scale = (s * d).sum(-1) / var_x.clamp_min(1e-300)
    scale = torch.where(var_x > 0, scale, torch.zeros_like(scale))
    translation = mu_y[:, 0] - scale[:, None] * (rotation @ mu_x[:, 0, :, None])[..., 0]
    nan = torch.full((), float("nan"), dtype=scale.dtype, device=scale.device)
    return Similarity(
        scale=torch.where(bad, nan, scale),
        rotation=torch.where(bad[:, None, None], nan, rotation),
        translation=torch.where(bad[:, None], nan, translation),
    )


def procrustes_align(
    pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """`pred` (B, N, 3) moved by the similarity that best fits it to `gt` (valid points only)."""
    return similarity_procrustes(pred, gt, valid).apply(pred)


def pa_mpjpe(
    pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Procrustes-aligned MPJPE per sample, (B,).

    MPJPE after the best scale, rotation and translation of `pred` onto `gt`. Invariant to any
    similarity transform of `pred`; same unit as the inputs. NaN for a sample with fewer than
    3 valid joints (a similarity fits one or two points exactly: it scored 0).
    """
    w = _check(pred, gt, valid, "pa_mpjpe")
    aligned = procrustes_align(pred, gt, valid)
    out = _mean_error(_zero_invalid(aligned, w), _zero_invalid(gt, w), w)
    return torch.where((w > 0).sum(-1) >= 3, out, torch.full_like(out, float("nan")))


def vertex_error(
    pred: torch.Tensor, gt: torch.Tensor, align: str = "none", valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean per-vertex Euclidean error (PVE), (B,), for meshes of the same topology, (B, V, 3).

    align: "none" (as given), "translation" (centroids matched) or "procrustes" (PA-PVE).
    """
    w = _check(pred, gt, valid, "vertex_error")
    pred, gt = _zero_invalid(pred, w), _zero_invalid(gt, w)
    if align == "translation":
        wsum = w.sum(-1)[:, None, None]
        pred = (
            pred
            - (pred * w[..., None]).sum(1, keepdim=True) / wsum
            + (gt * w[..., None]).sum(1, keepdim=True) / wsum
        )
    elif align == "procrustes":
        pred = procrustes_align(pred, gt, valid)
    elif align != "none":
        raise ValueError(
            f"vertex_error: align must be 'none', 'translation' or 'procrustes', got {align!r}"
        )
    return _mean_error(pred, gt, w)
