"""gsplat backend: parity with the torch backend on CUDA (skipped without CUDA and gsplat)."""

from __future__ import annotations

import importlib.util
import math

import pytest
import torch

from gst.render.cpu_backend import CompositeSettings, rasterize_cpu
from gst.render.rasterize import rasterize
from gst.render.scenes import SplatScenes
from tests.test_render_rasterize import random_scene

HAS_CUDA_GSPLAT = torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None
needs_gsplat = pytest.mark.skipif(not HAS_CUDA_GSPLAT, reason="needs CUDA and gsplat")


def test_gsplat_backend_without_cuda_says_what_is_missing():
    if HAS_CUDA_GSPLAT:
        pytest.skip("gsplat and CUDA are available here")
    scene = random_scene(0, s=1, n=5, c=1, width=8, height=8, dtype=torch.float32)
    with pytest.raises(RuntimeError, match="gsplat"):
        rasterize(*scene, 8, 8, backend="gsplat")


def _scene_cuda(seed, max_opacity):
    scene = random_scene(seed, s=2, n=300, c=3, width=96, height=80, dtype=torch.float32)
    means, quats, scales, opac, colors, viewmats, ks = scene
    opac = opac.clamp(0.02, max_opacity)
    return [t.cuda() for t in (means, quats, scales, opac, colors, viewmats, ks)]


@pytest.mark.cuda
@needs_gsplat
def test_gsplat_matches_torch_with_gsplat_footprint_and_clamp():
    """With gsplat's own footprint (alpha >= 1/255 only) and 0.999 clamp the torch backend is
    the same renderer: images agree to float32 precision."""
    from gst.render.gsplat_backend import rasterize_gsplat

    scene = _scene_cuda(0, max_opacity=1.0)
    g_rgb, g_alpha, g_depth = rasterize_gsplat(SplatScenes(*scene, 96, 80, 0.01))
    c_rgb, c_alpha, c_dsum = rasterize_cpu(
        SplatScenes(*scene, 96, 80, 0.01), CompositeSettings(sigma_cutoff=math.inf, alpha_max=0.999)
    )
    c_depth = c_dsum / c_alpha.clamp_min(1e-10)
    torch.testing.assert_close(g_rgb, c_rgb, atol=2e-4, rtol=0)
    torch.testing.assert_close(g_alpha, c_alpha, atol=2e-4, rtol=0)
    torch.testing.assert_close(g_depth, c_depth, atol=2e-3, rtol=1e-4)


@pytest.mark.cuda
@needs_gsplat
def test_auto_backend_parity_and_gradients():
    """rasterize(auto) on CUDA uses gsplat; with opacities <= 0.35 the 3-sigma cut and the
    0.99 clamp never bind, so both backends agree, gradients included."""
    scene = _scene_cuda(1, max_opacity=0.35)
    bgs = torch.rand(2, 3, 3, device="cuda")

    def run(backend, tensors):
        inputs = [t.clone().requires_grad_(True) for t in tensors]
        out = rasterize(*inputs, 96, 80, backgrounds=bgs, backend=backend)
        w = torch.rand(
            out.rgb.shape, generator=torch.Generator("cuda").manual_seed(0), device="cuda"
        )
        ((out.rgb * w).sum() + out.alpha.sum()).backward()
        return out, [t.grad for t in inputs]

    g_out, g_grads = run("auto", scene)
    c_out, c_grads = run("torch", scene)
    torch.testing.assert_close(g_out.rgb, c_out.rgb, atol=2e-4, rtol=0)
    torch.testing.assert_close(g_out.alpha, c_out.alpha, atol=2e-4, rtol=0)
    for name, g, c in zip(
        ("means", "quats", "scales", "opacities", "colors"), g_grads, c_grads, strict=False
    ):
        rel = (g - c).norm() / c.norm().clamp_min(1e-12)
        assert rel < 1e-3, f"gradient of {name} differs by {rel:.2e} (relative)"


@pytest.mark.cuda
@needs_gsplat
def test_default_conventions_differ_from_gsplat_only_by_the_faint_ring():
    """Default torch conventions (3-sigma cut, clamp 0.99) against gsplat: the only difference
    is the 3-3.33 sigma ring (alpha <= 0.011 per Gaussian) and the clamp of opaque centres."""
    from gst.render.gsplat_backend import rasterize_gsplat

    scene = _scene_cuda(2, max_opacity=0.98)
    g_rgb, g_alpha, _ = rasterize_gsplat(SplatScenes(*scene, 96, 80, 0.01))
    c_rgb, c_alpha, _ = rasterize_cpu(SplatScenes(*scene, 96, 80, 0.01))
    diff = (g_alpha - c_alpha).abs()
    assert diff.max() < 0.05
    assert diff.mean() < 2e-3


def test_the_environment_chooses_what_auto_means(monkeypatch):
    scene = random_scene(2, s=1, n=20, c=2, width=12, height=10, dtype=torch.float32)
    monkeypatch.setenv("GST_RENDER_BACKEND", "bogus")
    with pytest.raises(ValueError, match="GST_RENDER_BACKEND"):
        rasterize(*scene, 12, 10)
    monkeypatch.setenv("GST_RENDER_BACKEND", "torch")
    forced = rasterize(*scene, 12, 10)
    torch.testing.assert_close(forced.rgb, rasterize(*scene, 12, 10, backend="torch").rgb)
    monkeypatch.setenv("GST_RENDER_BACKEND", "gsplat")  # CPU tensors: gsplat cannot take them
    with pytest.raises(RuntimeError, match="gsplat"):
        rasterize(*scene, 12, 10)
