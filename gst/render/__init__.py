"""Differentiable Gaussian rasterisation (torch on any device, gsplat on CUDA) and PLY export."""

from gst.render.ply import GaussianCloud, read_gaussians_ply, write_gaussians_ply
from gst.render.rasterize import RenderOutput, rasterize

__all__ = [
    "GaussianCloud",
    "RenderOutput",
    "rasterize",
    "read_gaussians_ply",
    "write_gaussians_ply",
]
