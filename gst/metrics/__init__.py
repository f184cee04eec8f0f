"""Evaluation metrics and the perceptual loss.

- `lpips`: LPIPS v0.1 (AlexNet / VGG16) in plain torch, weights from `fetch_lpips_weights`.
- `image`: PSNR, SSIM, and SHERF-style metrics inside the projected 3D body box.
- `pose`: MPJPE, PA-MPJPE (similarity Procrustes), per-vertex error. Distances are in the
  inputs' unit (metres in this pipeline).
"""

from typing import TYPE_CHECKING

from gst.lazy import lazy_exports

# imported on first use (gst.lazy): `python -m gst.metrics.lpips` found the module already
# imported by this package and runpy warned of "unpredictable behaviour"
if TYPE_CHECKING:
    from gst.metrics.image import (
        BoxMetrics,
        BoxRegion,
        box_corners,
        masked_bbox_metrics,
        points_box_corners,
        project_box_region,
        psnr,
        ssim,
    )
    from gst.metrics.lpips import LPIPS, LPIPSWeightsMissing, fetch_lpips_weights, load_lpips
    from gst.metrics.pose import (
        Similarity,
        mpjpe,
        pa_mpjpe,
        procrustes_align,
        similarity_procrustes,
        vertex_error,
    )

__all__ = [
    "LPIPS",
    "BoxMetrics",
    "BoxRegion",
    "LPIPSWeightsMissing",
    "Similarity",
    "box_corners",
    "fetch_lpips_weights",
    "load_lpips",
    "masked_bbox_metrics",
    "mpjpe",
    "pa_mpjpe",
    "points_box_corners",
    "procrustes_align",
    "project_box_region",
    "psnr",
    "similarity_procrustes",
    "ssim",
    "vertex_error",
]

__getattr__, __dir__ = lazy_exports(__name__, __file__)
