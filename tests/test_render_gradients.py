"""Gradients of the torch rasteriser: gradcheck in float64, and finite values on hard inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.render.rasterize import rasterize
from tests.test_render_rasterize import look_at, random_scene


@pytest.fixture(autouse=True)
def _one_thread():
    """gradcheck runs thousands of tiny renders; on a loaded 2-core machine each multi-threaded
    torch op then waits tens of ms for a second thread, so pin these tests to one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _intrinsics(ks):
    """(..., 3, 3) -> (..., 4) fx, fy, cx, cy: gradcheck must not perturb the skew entry."""
    return torch.stack([ks[..., 0, 0], ks[..., 1, 1], ks[..., 0, 2], ks[..., 1, 2]], dim=-1)


def _leaves(means, quats, scales, opac, colors, viewmats, ks, bgs):
    """Fresh leaf copies (requires_grad) of the renderer's inputs, with ks as `_intrinsics`."""
    tensors = (means, quats, scales, opac, colors, viewmats, _intrinsics(ks), bgs)
    return [t.clone().requires_grad_(True) for t in tensors]


def _render_all(width, height, near=0.01):
    def fn(means, quats, scales, opac, colors, viewmats, intr, bgs):
        fx, fy, cx, cy = intr.unbind(-1)
        zero, one = torch.zeros_like(fx), torch.ones_like(fx)
        ks = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1)
        ks = ks.reshape(*fx.shape, 3, 3)
        out = rasterize(means, quats, scales, opac, colors, viewmats, ks, width, height,
                        backgrounds=bgs, backend="torch", near=near)  # fmt: skip
        return out.rgb, out.alpha, out.depth

    return fn


@pytest.mark.parametrize("seed, cameras, fast_mode", [(0, 1, False), (1, 2, True)])
def test_gradcheck_small_scene(seed, cameras, fast_mode):
    """Full Jacobian check on one small view; a random-projection (fast mode) check on two."""
    scene = random_scene(seed + 10, s=1, n=8, c=cameras, width=10, height=8)
    means, quats, scales, opac, colors, viewmats, ks = scene
    # Larger Gaussians so that every one of them covers pixels in this tiny image.
    scales = scales * 3.0
    opac = opac.clamp(0.05, 0.95)
    g = torch.Generator().manual_seed(seed)
    bgs = torch.rand(1, cameras, 3, dtype=torch.float64, generator=g)
    inputs = _leaves(means, quats, scales, opac, colors, viewmats, ks, bgs)
    out = _render_all(10, 8)(*inputs)
    assert out[1].max() > 0.3
    assert torch.autograd.gradcheck(
        _render_all(10, 8), inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast_mode
    )


def test_gradcheck_occlusion_and_early_stop():
    """Opaque overlapping Gaussians: the transmittance stop and alpha clamp are active."""
    g = torch.Generator().manual_seed(3)
    n = 7
    means = torch.zeros(1, n, 3, dtype=torch.float64)
    means[..., 2] = torch.linspace(2.0, 2.6, n, dtype=torch.float64)
    means[..., :2] = 0.02 * torch.randn(1, n, 2, dtype=torch.float64, generator=g)
    quats = torch.randn(1, n, 4, dtype=torch.float64, generator=g)
    scales = 0.03 + 0.02 * torch.rand(1, n, 3, dtype=torch.float64, generator=g)
    opac = torch.tensor([[0.97, 0.9, 0.95, 1.0, 0.92, 0.96, 0.9]], dtype=torch.float64)
    colors = torch.rand(1, n, 3, dtype=torch.float64, generator=g)
    viewmats = torch.tensor(look_at([0.05, 0.02, 0.0], [0.0, 0.0, 2.0]))[None, None]
    ks = torch.tensor([[[[30.0, 0, 4.5], [0, 30.0, 3.5], [0, 0, 1]]]], dtype=torch.float64)
    bgs = torch.rand(1, 1, 3, dtype=torch.float64, generator=g)
    inputs = _leaves(means, quats, scales, opac, colors, viewmats, ks, bgs)
    out = _render_all(10, 8)(*inputs)
    assert out[1].max() > 1 - 1e-3  # transmittance reached the stop somewhere
    assert torch.autograd.gradcheck(_render_all(10, 8), inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


def _hard_scene(dtype=torch.float32):
    """Every degenerate case the issue lists, in one camera looking down +z from the origin."""
    rows = [
        # mean xyz,           quat wxyz,          scale xyz,          opacity
        ([0.0, 0.0, -1.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8),  # behind the camera
        ([0.0, 0.0, 0.0], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8),  # at the camera centre
        ([0.001, 0.0, 0.01], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8),  # exactly at near
        ([0.1, 0.0, 0.0100001], [1, 0, 0, 0], [0.05, 0.05, 0.05], 0.8),  # just past near
        ([0.0, 0.1, 2.0], [1, 0, 0, 0], [0.0, 0.0, 0.0], 0.9),  # zero scales
        ([0.0, 0.0, 3.0], [1, 0, 0, 0], [1e6, 1e6, 1e6], 0.5),  # huge scales
        ([0.1, 0.0, 3.0], [1, 0, 0, 0], [1e6, 0.0, 0.0], 0.5),  # huge and zero (a needle)
        ([-0.1, 0.0, 2.0], [0, 0, 0, 0], [0.05, 0.02, 0.01], 0.9),  # zero quaternion
        ([0.1, 0.1, 2.0], [30, -4, 7, 1], [0.05, 0.02, 0.01], 0.9),  # unnormalised
        ([0.0, -0.1, 2.0], [1, 1e-9, 0, 0], [0.05, 0.02, 0.01], 0.0),  # opacity 0
        ([0.05, -0.1, 2.5], [0.3, 0.2, 0, 1], [0.05, 0.02, 0.01], 1.0),  # opacity 1
        ([50.0, 0.0, 0.02], [1, 0, 0, 0], [0.05, 0.05, 0.05], 1.0),  # far off-axis, near
    ]
    t = lambda col: torch.tensor([r[col] for r in rows], dtype=dtype)[None]  # noqa: E731
    means, quats, scales, opac = t(0), t(1), t(2), t(3)
    colors = torch.rand(1, len(rows), 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    viewmats = torch.eye(4, dtype=dtype)[None, None]
    ks = torch.tensor([[[[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]]]], dtype=dtype)
    return means, quats, scales, opac, colors, viewmats, ks


def _assert_finite_with_grads(scene, width, height):
    inputs = [t.clone().requires_grad_(True) for t in scene]
    out = rasterize(*inputs, width, height, backend="torch")
    for name, v in (("rgb", out.rgb), ("alpha", out.alpha), ("depth", out.depth)):
        assert torch.isfinite(v).all(), f"{name} not finite"
    g = torch.Generator().manual_seed(1)
    loss = sum((v * torch.rand(v.shape, generator=g, dtype=v.dtype)).sum()
               for v in (out.rgb, out.alpha, out.depth))  # fmt: skip
    loss.backward()
    names = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")
    for name, t in zip(names, inputs, strict=True):
        assert t.grad is not None and torch.isfinite(t.grad).all(), f"grad of {name} not finite"
    return out, inputs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_gaussians_give_finite_outputs_and_gradients(dtype):
    out, inputs = _assert_finite_with_grads(_hard_scene(dtype), 32, 24)
    assert out.alpha.max() > 0.9  # the huge Gaussians cover the image
    # Culled Gaussians (behind / at the camera) get exactly zero gradient.
    assert inputs[0].grad[0, :2].abs().max() == 0


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    log_scale=st.floats(-30.0, 30.0),
    z_shift=st.floats(-3.5, 1.0),
    quat_scale=st.sampled_from([0.0, 1e-20, 1.0, 1e20]),
    opacity=st.sampled_from([0.0, 1e-6, 1.0 / 255.0, 0.5, 1.0]),
)
def test_random_extremes_are_finite(seed, log_scale, z_shift, quat_scale, opacity):
    g = np.random.default_rng(seed)
    n = 10
    means = g.normal(0, 0.3, (1, n, 3))
    means[..., 2] += 3.0 + z_shift  # pushes some Gaussians to / behind the near plane
    quats = g.normal(size=(1, n, 4)) * quat_scale
    scales = np.exp(g.normal(np.log(0.03), 1.0, (1, n, 3)))
    scales[0, 0] = np.exp(log_scale)
    opac = g.uniform(0, 1, (1, n))
    opac[0, 1] = opacity
    colors = g.uniform(0, 1, (1, n, 3))
    viewmats = np.eye(4)[None, None]
    ks = np.array([[[[30.0, 0, 10.0], [0, 30.0, 8.0], [0, 0, 1]]]])
    scene = [torch.tensor(a, dtype=torch.float32)
             for a in (means, quats, scales, opac, colors, viewmats, ks)]  # fmt: skip
    _assert_finite_with_grads(scene, 20, 16)
