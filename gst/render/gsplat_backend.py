"""gsplat backend (CUDA): maps our conventions onto `gsplat.rasterization` (gsplat 1.5.x).

gsplat is an optional dependency (the `cuda` extra) and is imported only when this backend runs.

Mapping:
- Pixel centres: gsplat samples pixel j at j + 0.5, we at j; we pass cx + 0.5, cy + 0.5.
- eps2d = 0.3, rasterize_mode "classic" (no antialiasing compensation), near_plane = `near`,
  render_mode "RGB+ED": gsplat's expected depth is sum w z / alpha, our normalised depth.
- Backgrounds are composited by the caller (rgb + (1 - alpha) bg), not passed to gsplat,
  whose background tensor must match the rendered channel count (4 with depth).
- Quaternions: gsplat normalises them itself but a zero quaternion would give NaN; we pass
  the identity instead. Scales are clamped to `SCALE_MAX` as on the torch backend.
- Scenes are rendered one at a time (a loop over S, not over Gaussians or pixels), which
  works with every gsplat 1.x release; cameras of a scene go in one call.

Known differences from the torch backend (inherent to gsplat's kernels):
- gsplat clamps alpha at 0.999, not 0.99: they differ where o exp(-power) > 0.99.
- gsplat has no per-pixel 3-sigma cut: inside a touched 16x16 tile it keeps every pixel with
  alpha >= 1/255, which reaches sqrt(2 ln(255 o)) sigma (up to 3.33 sigma). For opacities
  above exp(4.5) / 255 ~= 0.353 it therefore adds a faint ring (alpha <= o e^-4.5 <= 0.011)
  between 3 and 3.33 sigma. The torch backend with `CompositeSettings(sigma_cutoff=inf,
  alpha_max=0.999)` reproduces gsplat exactly; the parity test checks both ways.
- gsplat stops at transmittance <= 1e-4, we at < 1e-4 (a measure-zero difference).
"""

from __future__ import annotations

import torch
from torch import Tensor

from gst.render.conventions import LOWPASS_EPS2D, QUAT_EPS, SCALE_MAX
from gst.render.scenes import SplatScenes


def rasterize_gsplat(scenes: SplatScenes, *, packed: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Render validated batched inputs with gsplat.

    Returns (colour sum (S, C, H, W, 3) without background, alpha (S, C, H, W),
    normalised expected depth (S, C, H, W)).
    """
    try:
        from gsplat import rasterization
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise RuntimeError(
            "rasterize(backend='gsplat') needs gsplat (pip install 'gst-capture[cuda]') and a "
            "CUDA device"
        ) from exc
    means, quats, scales, Ks = scenes.means, scenes.quats, scenes.scales, scenes.Ks
    if means.device.type != "cuda":
        raise RuntimeError(f"rasterize(backend='gsplat') needs CUDA tensors, got {means.device}")

    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    norm = torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    safe_quats = torch.where(norm > QUAT_EPS, quats, identity)
    safe_scales = scales.clamp(max=SCALE_MAX)
    Ks_half = Ks.clone()
    Ks_half[..., 0, 2] = Ks[..., 0, 2] + 0.5
    Ks_half[..., 1, 2] = Ks[..., 1, 2] + 0.5

    rgbs, alphas, depths = [], [], []
    for s in range(means.shape[0]):
        # gsplat's kernels index raw memory: hand them contiguous tensors (inputs may be
        # expanded views, e.g. one camera set shared by all scenes).
        render, alpha, _meta = rasterization(
            means=means[s].contiguous(),
            quats=safe_quats[s].contiguous(),
            scales=safe_scales[s].contiguous(),
            opacities=scenes.opacities[s].contiguous(),
            colors=scenes.colors[s].contiguous(),
            viewmats=scenes.viewmats[s].contiguous(),
            Ks=Ks_half[s].contiguous(),
            width=scenes.width,
            height=scenes.height,
            near_plane=scenes.near,
            eps2d=LOWPASS_EPS2D,
            packed=packed,
            render_mode="RGB+ED",
            rasterize_mode="classic",
            backgrounds=None,
        )
        rgbs.append(render[..., :3])
        depths.append(render[..., 3])
        alphas.append(alpha[..., 0])
    return torch.stack(rgbs), torch.stack(alphas), torch.stack(depths)
