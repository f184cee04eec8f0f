"""Differentiable Gaussian rasterisation with one API and two backends.

`rasterize()` renders S scenes of N Gaussians each into C cameras per scene.

Conventions (identical on both backends):
- Gaussians: means in world metres, quaternions wxyz (normalised per Gaussian here; a zero
  quaternion means no rotation), linear scales (after exp), opacities in [0, 1] (after
  sigmoid), colours as given (no clamping, no spherical harmonics).
- Cameras: `viewmats` map world to camera (X_cam = R X_world + t), OpenCV axes (x right,
  y down, z forward); `Ks` are pinhole intrinsics without skew, no distortion.
- Pixel centres are integers (OpenCV and the reference 3DGS rasteriser): pixel (u, v) covers
  [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]. gsplat samples pixel j at j + 0.5, so its backend
  is called with cx + 0.5, cy + 0.5; both backends then evaluate the same points.
- EWA splatting as in 3DGS: a 0.3 px^2 low-pass on the 2D covariance, a 3-sigma footprint,
  alpha = min(0.99, o exp(-0.5 d^T Sigma^-1 d)), contributions with alpha < 1/255 skipped,
  front-to-back by the depth of each centre, and compositing stops before the Gaussian that
  would take transmittance below 1e-4. Gaussians closer than `near` are culled.
- Outputs: rgb = sum_i w_i c_i + (1 - alpha) * background; alpha = 1 - final transmittance;
  depth = sum_i w_i z_i / alpha, i.e. the *normalised* expected camera z (gsplat's "ED"),
  and 0 where alpha is 0.

Backends: "torch" (pure torch, tile-binned, any device; `gst.render.cpu_backend`) and
"gsplat" (CUDA, optional `cuda` extra; `gst.render.gsplat_backend`). "auto" picks gsplat for
CUDA tensors when it is importable, else torch; the environment variable
`GST_RENDER_BACKEND=torch|gsplat` makes "auto" mean that backend instead (training and evaluation
call "auto": compare the two, or step around a gsplat build that misbehaves). Known gsplat
differences are listed in `gst.render.gsplat_backend`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from gst.render.cpu_backend import rasterize_cpu
from gst.render.scenes import SplatScenes

BACKENDS = ("auto", "torch", "cpu", "gsplat")


@dataclass
class RenderOutput:
    """Rendered images. Shapes (S, C, H, W[, 3]); without the S dim for unbatched inputs."""

    rgb: Tensor  # (S, C, H, W, 3) composited colour over the background
    alpha: Tensor  # (S, C, H, W) accumulated opacity, 1 - final transmittance
    depth: Tensor  # (S, C, H, W) normalised expected camera z (sum w z / alpha); 0 if alpha 0


def _check_shape(name: str, t: Tensor, expected: tuple, batched: bool) -> None:
    exp = expected if batched else expected[1:]
    ok = t.ndim == len(exp) and all(e is None or e == d for e, d in zip(exp, t.shape, strict=True))
    if not ok:
        dims = ", ".join("?" if e is None else str(e) for e in exp)
        raise ValueError(f"rasterize: {name} has shape {tuple(t.shape)}, expected ({dims})")


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA build
        return False
    return True


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: unknown backend {backend!r}, expected one of {BACKENDS}")
    if backend == "cpu":
        return "torch"
    if backend == "auto":
        forced = os.environ.get("GST_RENDER_BACKEND", "").strip().lower()
        if forced:
            if forced not in ("torch", "gsplat"):
                raise ValueError(
                    f"GST_RENDER_BACKEND={forced!r}: expected 'torch' or 'gsplat' (or unset)"
                )
            return forced
        return "gsplat" if device.type == "cuda" and _gsplat_available() else "torch"
    return backend


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor | None = None,
    backend: str = "auto",
    near: float = 0.01,
) -> RenderOutput:
    """Render Gaussians into cameras, differentiably in every tensor input.

    Args:
        means: (S, N, 3) centres, world metres. Unbatched (N, 3) is accepted together with
            unbatched everything else (no S dim); outputs then have no S dim either.
        quats: (S, N, 4) wxyz rotations (normalised here).
        scales: (S, N, 3) linear standard deviations, metres.
        opacities: (S, N) in [0, 1].
        colors: (S, N, 3).
        viewmats: (S, C, 4, 4) world-to-camera.
        Ks: (S, C, 3, 3) intrinsics, integer pixel centres, no skew.
        width, height: image size in pixels.
        backgrounds: (S, C, 3) colour behind the Gaussians; None means black.
        backend: "auto", "torch" (alias "cpu") or "gsplat".
        near: Gaussians with camera z below this are culled (metres, > 0).

    Returns:
        RenderOutput with rgb (S, C, H, W, 3), alpha (S, C, H, W), depth (S, C, H, W).
    """
    batched = means.ndim == 3
    s = means.shape[0] if batched else 1
    n = means.shape[-2] if means.ndim >= 2 else -1
    _check_shape("means", means, (None, None, 3), batched)
    _check_shape("quats", quats, (s, n, 4), batched)
    _check_shape("scales", scales, (s, n, 3), batched)
    _check_shape("opacities", opacities, (s, n), batched)
    _check_shape("colors", colors, (s, n, 3), batched)
    _check_shape("viewmats", viewmats, (s, None, 4, 4), batched)
    c = viewmats.shape[-3]
    _check_shape("Ks", Ks, (s, c, 3, 3), batched)
    if backgrounds is not None:
        _check_shape("backgrounds", backgrounds, (s, c, 3), batched)
    if not (
        isinstance(width, (int, np.integer))
        and isinstance(height, (int, np.integer))
        and not isinstance(width, bool)
        and not isinstance(height, bool)
        and width > 0
        and height > 0
    ):
        raise ValueError(
            f"rasterize: width and height must be positive ints, got {width!r}, {height!r}"
        )
    width, height = int(width), int(height)
    if not near > 0:
        raise ValueError(f"rasterize: near must be > 0 (metres), got {near}")
    tensors = {
        "means": means, "quats": quats, "scales": scales, "opacities": opacities,
        "colors": colors, "viewmats": viewmats, "Ks": Ks,
    }  # fmt: skip
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    if not means.dtype.is_floating_point:
        raise ValueError(f"rasterize: means must be floating point, got {means.dtype}")
    for name, t in tensors.items():
        if t.dtype != means.dtype or t.device != means.device:
            raise ValueError(
                f"rasterize: {name} is {t.dtype} on {t.device}, expected {means.dtype} on "
                f"{means.device} like means"
            )
    # a NaN or infinite camera renders a blank image and NaN gradients on every Gaussian: one
    # bad camera silently spoils a training step
    for name in ("viewmats", "Ks"):
        if not bool(torch.isfinite(tensors[name].detach()).all()):
            raise ValueError(f"rasterize: {name} holds NaN or Inf (a broken camera)")
    skew = Ks[..., 0, 1].detach().abs()
    if bool((skew > 1e-9 * Ks[..., 0, 0].detach().abs()).any()):
        raise ValueError("rasterize: Ks has non-zero skew K[0, 1]; skewed cameras are unsupported")
    if bool((Ks[..., 0, 0] <= 0).any() or (Ks[..., 1, 1] <= 0).any()):
        raise ValueError(
            "rasterize: Ks must have positive focal lengths fx = K[0, 0], fy = K[1, 1]"
        )

    # Rasterise in the inputs' own dtype even inside an autocast region (bf16 training): with
    # bf16 matmuls the projection and the transmittance sums lose far more than the image is worth.
    with torch.autocast(means.device.type, enabled=False):
        if not batched:
            means, quats, scales, opacities, colors, viewmats, Ks = (
                t[None] for t in (means, quats, scales, opacities, colors, viewmats, Ks)
            )
            backgrounds = None if backgrounds is None else backgrounds[None]

        scenes = SplatScenes(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, near
        )
        chosen = _resolve_backend(backend, means.device)
        if chosen == "gsplat":
            from gst.render.gsplat_backend import rasterize_gsplat

            color_sum, alpha, depth = rasterize_gsplat(scenes)
        else:
            color_sum, alpha, depth_sum = rasterize_cpu(scenes)
            # 1e-10 is 0 in float16: 0 / 0 made every empty pixel's depth NaN (and its gradient)
            floor = max(1e-10, torch.finfo(alpha.dtype).tiny)
            depth = depth_sum / alpha.clamp_min(floor)

        rgb = color_sum
        if backgrounds is not None:
            rgb = rgb + (1.0 - alpha)[..., None] * backgrounds[:, :, None, None, :]
        out = RenderOutput(rgb=rgb, alpha=alpha, depth=depth)
        if not batched:
            out = RenderOutput(rgb=out.rgb[0], alpha=out.alpha[0], depth=out.depth[0])
        return out
