"""Numerical stability of the torch rasteriser on whole scenes of degenerate Gaussians (the mixed
single-scene case is in test_render_gradients.py): every Gaussian tiny, huge, transparent, behind
the camera or on its plane, or no Gaussian at all. Where the answer is known in closed form
(a point-like Gaussian is the 0.3 px^2 low-pass blob; a huge one is flat), it is checked."""

from __future__ import annotations

import math

import pytest
import torch

from gst.render.conventions import ALPHA_MAX, LOWPASS_EPS2D
from gst.render.rasterize import rasterize

W, H = 24, 20
FOCAL = 30.0


def _camera(dtype):
    viewmats = torch.eye(4, dtype=dtype)[None]  # camera at the origin looking down +z
    Ks = torch.tensor([[[FOCAL, 0, 11.0], [0, FOCAL, 9.0], [0, 0, 1]]], dtype=dtype)
    return viewmats, Ks


def _scene(n, dtype, seed=0, z=3.0):
    g = torch.Generator().manual_seed(seed)
    means = 0.3 * torch.randn(n, 3, generator=g, dtype=dtype) + torch.tensor([0, 0, z], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.full((n, 3), 0.05, dtype=dtype)
    opac = torch.full((n,), 0.8, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


def _render(means, quats, scales, opac, colors, background=True):
    """Render with gradients on every input; return outputs and the inputs' gradients."""
    dtype = means.dtype
    viewmats, Ks = _camera(dtype)
    inputs = [
        t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, viewmats, Ks)
    ]
    bg = torch.tensor([[0.2, 0.5, 0.7]], dtype=dtype, requires_grad=True) if background else None
    out = rasterize(*inputs, W, H, backgrounds=bg, backend="torch")
    for name, v in (("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth)):
        assert torch.isfinite(v).all(), f"{name} not finite"
    g = torch.Generator().manual_seed(1)
    loss = sum(
        (v * torch.rand(v.shape, generator=g, dtype=dtype)).sum()
        for v in (out.rgb, out.alpha, out.depth)
    )
    loss.backward()
    names = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")
    for name, t in zip(names, inputs, strict=True):
        assert t.grad is not None and torch.isfinite(t.grad).all(), f"gradient of {name} not finite"
    if bg is not None:
        assert torch.isfinite(bg.grad).all()
    return out, dict(zip(names, (t.grad for t in inputs), strict=True)), bg


def _assert_blank(out, grads, bg):
    """Nothing drawn: alpha and depth exactly 0, rgb exactly the background, no gradient."""
    assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
    expected = (
        bg.detach()[:, None, None, :].expand_as(out.rgb)
        if bg is not None
        else torch.zeros_like(out.rgb)
    )
    assert torch.equal(out.rgb.detach(), expected)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert grads[name].abs().sum() == 0, name
    if bg is not None:  # the whole image is background: its gradient is the loss weights' sum
        assert (bg.grad > 0).all()


DTYPES = [torch.float32, torch.float64]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("background", [True, False])
def test_all_opacities_zero(dtype, background):
    means, quats, scales, _, colors = _scene(40, dtype)
    _assert_blank(*_render(means, quats, scales, torch.zeros(40, dtype=dtype), colors, background))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("where", ["behind", "camera_plane", "camera_centre", "just_before_near"])
def test_every_gaussian_culled(dtype, where):
    """Gaussians behind the camera, exactly on its plane (z = 0, where x/z is infinite), at its
    centre, or just short of the near plane: none is drawn and none gets a NaN gradient."""
    means, quats, scales, opac, colors = _scene(40, dtype)
    if where == "behind":
        means = means * torch.tensor([1.0, 1.0, -1.0], dtype=dtype)
    elif where == "camera_plane":
        means = means * torch.tensor([1.0, 1.0, 0.0], dtype=dtype)
    elif where == "camera_centre":
        means = torch.zeros_like(means)
    else:
        means = means * torch.tensor([1.0, 1.0, 0.0], dtype=dtype) + torch.tensor(
            [0, 0, 0.009], dtype=dtype
        )
    _assert_blank(*_render(means, quats, scales, opac, colors))


@pytest.mark.parametrize("dtype", DTYPES)
def test_no_gaussians_at_all(dtype):
    empty = [torch.zeros(0, k, dtype=dtype) for k in (3, 4, 3)]
    _assert_blank(*_render(*empty, torch.zeros(0, dtype=dtype), torch.zeros(0, 3, dtype=dtype)))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e-9])
def test_point_like_gaussians_are_the_lowpass_blob(dtype, scale):
    """A Gaussian far below a pixel is drawn as the 0.3 px^2 filter alone:
    alpha(d) = o exp(-|d|^2 / (2 * 0.3)) around its centre, computed here by hand."""
    o = 0.7
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=dtype)  # projects exactly onto pixel (11, 9)
    out, _, _ = _render(
        means,
        torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
        torch.full((1, 3), scale, dtype=dtype),
        torch.tensor([o], dtype=dtype),
        torch.ones(1, 3, dtype=dtype),
        background=False,
    )
    alpha = out.alpha.detach()[0]
    assert alpha[9, 11].item() == pytest.approx(o, rel=1e-5)
    assert alpha[9, 12].item() == pytest.approx(o * math.exp(-1 / (2 * LOWPASS_EPS2D)), rel=1e-4)
    assert alpha[10, 12].item() == pytest.approx(o * math.exp(-2 / (2 * LOWPASS_EPS2D)), rel=1e-4)
    # Beyond the alpha >= 1/255 footprint nothing is drawn.
    assert alpha[9, 14].item() == 0.0 and alpha.sum().item() < 4 * o


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", [1e4, 1e6, 1e30])
def test_huge_gaussians_are_flat(dtype, scale):
    """A Gaussian kilometres (up to 1e30 m, clamped to SCALE_MAX) wide in front of the camera is
    flat over a 24 px image: alpha = o everywhere, depth = its z, colour = o c + (1 - o) bg.
    (Its footprint is >= 1e5 px wide, so the fall-off over the image is below 1e-7.)"""
    o = 0.6
    color = torch.tensor([[0.9, 0.1, 0.4]], dtype=dtype)
    out, grads, bg = _render(
        torch.tensor([[0.1, -0.2, 3.0]], dtype=dtype),
        torch.tensor([[0.9, 0.1, -0.3, 0.2]], dtype=dtype),
        torch.full((1, 3), scale, dtype=dtype),
        torch.tensor([o], dtype=dtype),
        color,
    )
    tol = 2e-6
    torch.testing.assert_close(out.alpha.detach(), torch.full_like(out.alpha, o), atol=tol, rtol=0)
    torch.testing.assert_close(
        out.depth.detach(), torch.full_like(out.depth, 3.0), atol=tol * 3, rtol=0
    )
    expected = o * color + (1 - o) * bg.detach()
    torch.testing.assert_close(
        out.rgb.detach(), expected[:, None, None, :].expand_as(out.rgb), atol=tol, rtol=0
    )
    assert grads["opacities"].abs().sum() > 0  # still trainable


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", ["tiny", "huge", "needle", "pancake", "mixed"])
def test_many_extreme_scales(dtype, kind):
    """Forty Gaussians at once with extreme or wildly anisotropic scales, some overlapping."""
    means, quats, _, opac, colors = _scene(40, dtype, seed=2)
    g = torch.Generator().manual_seed(3)
    scales = {
        "tiny": torch.full((40, 3), 1e-12),
        "huge": torch.full((40, 3), 1e8),
        "needle": torch.tensor([1e5, 1e-9, 1e-9]).expand(40, 3),
        "pancake": torch.tensor([1e5, 1e5, 0.0]).expand(40, 3),
        "mixed": torch.exp(torch.empty(40, 3).uniform_(-60, 60, generator=g)),
    }[kind].to(dtype)
    out, _, _ = _render(means, quats, scales, opac, colors)
    assert out.alpha.max() > 0.1  # something was drawn


@pytest.mark.parametrize("dtype", DTYPES)
def test_opaque_stack_saturates_without_overflow(dtype):
    """Two hundred fully opaque, coincident Gaussians: alpha per Gaussian is clamped to 0.99,
    compositing stops before transmittance would fall below 1e-4, so only one or two of them are
    composited (0.01 * 0.01 sits right at the limit) and alpha is 0.99 or 0.9999."""
    n = 200
    means = torch.tensor([0.0, 0.0, 2.0], dtype=dtype).expand(n, 3)
    out, _, _ = _render(
        means,
        torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(n, 4),
        torch.full((n, 3), 0.5, dtype=dtype),
        torch.ones(n, dtype=dtype),
        torch.rand(n, 3, dtype=dtype, generator=torch.Generator().manual_seed(0)),
    )
    centre = out.alpha.detach()[0, 9, 11].item()
    assert min(abs(centre - ALPHA_MAX), abs(centre - (1 - (1 - ALPHA_MAX) ** 2))) < 1e-6


def test_float16_empty_pixels_have_depth_zero():
    """Half-precision inputs: depth is 0 (not 0 / 0 = NaN) where nothing is drawn, and the
    gradients stay finite (the 1e-10 floor on alpha underflowed to 0 in float16)."""
    out, _, _ = _render(*_scene(6, torch.float16))  # asserts finite outputs and gradients
    empty = out.alpha.detach() == 0
    assert empty.any() and out.depth.detach()[empty].abs().max() == 0
