"""The rasteriser backends' one input: batched, validated Gaussians and cameras.

`gst.render.rasterize.rasterize` checks shapes, dtypes and intrinsics (its docstring has the
shapes and conventions) and hands both backends this, so they share one signature.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class SplatScenes:
    """S scenes of N Gaussians, each seen by its C cameras (always batched)."""

    means: Tensor  # (S, N, 3) world metres
    quats: Tensor  # (S, N, 4) wxyz
    scales: Tensor  # (S, N, 3) linear standard deviations, metres
    opacities: Tensor  # (S, N) in [0, 1]
    colors: Tensor  # (S, N, 3)
    viewmats: Tensor  # (S, C, 4, 4) world to camera
    Ks: Tensor  # (S, C, 3, 3) intrinsics, integer pixel centres, no skew
    width: int
    height: int
    near: float  # Gaussians with camera z below this are culled (metres)
