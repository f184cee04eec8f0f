"""Numerical stability of the whole GST path (tiny preset): network -> 6D -> LBS -> posed
Gaussians -> rasteriser -> losses -> gradients, under bf16 autocast, with degenerate head
outputs (zero / collinear 6D, collapsed camera scale, transparent / saturated Gaussians), on
all-black images with empty masks, and for batches of 1 and 256 (pose-only)."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.metrics.lpips import LPIPS
from gst.metrics.lpips_weights import default_weights_path
from gst.model.presets import get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.steps import multiview_step
from gst.train.trainer import TrainConfig
from gst.train.views import sample_multiview
from tests.test_train_recipe import crop_set


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny batches of small ops: a second thread on a shared 2-core machine only adds waiting."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def setup():
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    # The heads start at gain 0.01 (outputs = their biases): give them full-size weights so the
    # outputs depend on the image and a precision loss would show.
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for lin in (
            net.smpl_head.decpose,
            net.smpl_head.decshape,
            net.smpl_head.deccam,
            *net.gaussian_head.heads.values(),
        ):
            bound = math.sqrt(6.0 / (lin.in_features + lin.out_features))
            lin.weight.copy_(torch.empty_like(lin.weight).uniform_(-bound, bound, generator=gen))
    return body, cfg, net, ids, groups


def _images(b: int, cfg, seed: int = 0) -> torch.Tensor:
    return torch.randn(b, 3, *cfg.image_size, generator=torch.Generator().manual_seed(seed))


# --- bf16 autocast ------------------------------------------------------------------------------

TOLERANCE = {  # max |bf16 - fp32| allowed, per output; bf16 keeps ~3 significant digits
    "body_pose_6d": 0.08,
    "rotmats": 0.05,
    "betas": 0.08,
    "cam": 0.05,
    "colors": 0.02,
    "quats": 0.05,
    "opacities": 0.02,
    "scales": 2e-3,
    "offsets": 5e-3,
}


def test_bf16_autocast_forward_is_finite_and_close_to_fp32(setup):
    _, cfg, net, _, _ = setup
    net.eval()
    x = _images(4, cfg)
    with torch.no_grad():
        ref = net(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = net(x)
    assert low.gaussians.scales.dtype == torch.bfloat16  # autocast really was active
    pairs = {
        k: (getattr(ref, k), getattr(low, k)) for k in ("body_pose_6d", "rotmats", "betas", "cam")
    }
    pairs.update(
        {
            k: (getattr(ref.gaussians, k), getattr(low.gaussians, k))
            for k in ("colors", "quats", "opacities", "scales", "offsets")
        }
    )
    for name, (a, b) in pairs.items():
        assert torch.isfinite(b).all(), name
        err = (a - b.float()).abs()
        assert err.max() <= TOLERANCE[name], (name, err.max().item())
        # And bf16 error is small next to how much the output changes from image to image.
        spread = (a - a.roll(1, dims=0)).abs().mean()
        assert err.mean() < 0.5 * spread, (name, err.mean().item(), spread.item())
    eye = torch.eye(3).expand_as(low.rotmats)
    assert (low.rotmats.float() @ low.rotmats.float().transpose(-1, -2) - eye).abs().max() < 1e-2


def test_pose_only_batches_of_1_and_256(setup):
    """Batch 256 through the pose-only path: finite, and a row equals the same image run alone
    (batch 1); bf16 on a slice of it stays close."""
    _, cfg, net, _, _ = setup
    net.eval()
    x = _images(256, cfg, seed=2)
    with torch.no_grad():
        full = net(x, with_gaussians=False)
        one = net(x[17:18], with_gaussians=False)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = net(x[:8], with_gaussians=False)
    assert full.gaussians is None and full.rotmats.shape == (256, 24, 3, 3)
    for out in (full, one, low):
        for name in ("rotmats", "betas", "cam"):
            assert torch.isfinite(getattr(out, name)).all(), name
    torch.testing.assert_close(one.rotmats, full.rotmats[17:18], atol=1e-4, rtol=0)
    torch.testing.assert_close(one.betas, full.betas[17:18], atol=1e-4, rtol=0)
    assert (low.rotmats.float() - full.rotmats[:8]).abs().max() <= TOLERANCE["rotmats"]


# --- full forward + backward on degenerate inputs and head outputs --------------------------------


def _degenerate(net, mode: str):
    """A copy of `net` whose heads emit one degenerate output for every image."""
    net = copy.deepcopy(net)
    head, gh = net.smpl_head, net.gaussian_head.heads
    with torch.no_grad():
        if mode in ("zero_6d", "collinear_6d"):
            head.decpose.weight.zero_()
            six = torch.zeros(24, 6)
            if mode == "collinear_6d":
                six[:, :3] = torch.tensor([0.3, -1.0, 0.2])
                six[:, 3:] = 2 * six[:, :3]
            head.decpose.bias.copy_(six.reshape(-1) - head.init_body_pose[0])
        elif mode == "collapsed_camera":  # s <= 0: clamped, the body lands far away
            head.deccam.weight.zero_()
            head.deccam.bias.copy_(torch.tensor([-3.0, 0.0, 0.0]))
        elif mode in ("transparent", "saturated"):  # sigmoid / tanh heads pinned at their bounds
            sign = -1.0 if mode == "transparent" else 1.0
            for name in ("opacity", "scale", "offset", "color"):
                gh[name].weight.zero_()
                gh[name].bias.fill_(sign * 1e4)
        elif mode == "zero_quaternions":
            gh["rotation"].weight.zero_()
            gh["rotation"].bias.zero_()
        elif mode != "none":
            raise ValueError(mode)
    return net


def _step(
    setup, net, *, black: bool, empty_masks: bool, lpips=None, render_size: int = 16, batch: int = 2
):
    body, cfg, _, ids, _ = setup
    crops = crop_set(n_frames=2, n_cams=3, size=64)
    if black:
        crops.images.zero_()
    if empty_masks:
        crops.masks.zero_()
    weights = LossWeights(lpips=0.01 if lpips is not None else 0.0)
    task = make_task(body, ids, cfg, crops.crop_size, weights, lpips=lpips)
    b = sample_multiview(
        crops, crops.groups(), torch.Generator().manual_seed(0), batch, 2, render_size
    )
    net.train()
    net.zero_grad(set_to_none=True)
    loss, parts = multiview_step(net, b, task)
    loss.backward()
    assert torch.isfinite(loss), {k: float(v) for k, v in parts.items()}
    for name, p in net.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), f"gradient of {name} not finite"
    return loss, parts


@pytest.mark.parametrize(
    "mode",
    [
        "none",
        "zero_6d",
        "collinear_6d",
        "collapsed_camera",
        "transparent",
        "saturated",
        "zero_quaternions",
    ],
)
def test_forward_backward_with_degenerate_heads(setup, mode):
    _step(setup, _degenerate(setup[2], mode), black=False, empty_masks=False)


@pytest.mark.parametrize("black, empty_masks", [(True, True), (True, False), (False, True)])
def test_forward_backward_on_black_images_and_empty_masks(setup, black, empty_masks):
    _step(setup, setup[2], black=black, empty_masks=empty_masks, batch=1)


def test_lpips_term_on_black_images_and_empty_masks(setup):
    """The LPIPS term sees a black target composited on the background and a render."""
    if not default_weights_path("alex").is_file():
        pytest.skip("LPIPS weights not cached; run `python -m gst.metrics.lpips fetch --net alex`")
    loss, parts = _step(
        setup,
        _degenerate(setup[2], "transparent"),
        black=True,
        empty_masks=True,
        lpips=LPIPS("alex"),
        render_size=32,
        batch=1,
    )
    # Transparent Gaussians render pure background, which is exactly the target: all zero.
    assert abs(float(parts["mse"])) < 1e-12 and abs(float(parts["lpips"])) < 1e-6


# --- bf16 training (TrainConfig.amp) ----------------------------------------------------------


def test_bf16_training_step_matches_fp32_and_trains(setup, tmp_path):
    """Under autocast only the network runs in bf16 (assemble and rasterize switch it off); this
    used to fail with a dtype mismatch inside rasterize."""
    body, cfg, net, ids, groups = setup
    loss32, _ = _step(setup, copy.deepcopy(net), black=False, empty_masks=False)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss16, _ = _step(setup, copy.deepcopy(net), black=False, empty_masks=False)
    assert loss16.item() == pytest.approx(loss32.item(), rel=0.05)

    crops = crop_set(n_frames=2, n_cams=3, size=64)
    model = copy.deepcopy(net)
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    summary = fit_gst(
        model,
        task,
        crops,
        TrainConfig(steps=2, batch_size=2, warmup_steps=1, val_every=2, amp=True),
        tmp_path,
        FitOptions(mode="multiview", num_targets=2, render_size=16, heldout_cameras=("c2",)),
        body_spec="random",
        vertex_ids=ids,
        group_index=groups,
    )
    assert summary.steps == 2 and summary.bad_steps == 0
    assert all(math.isfinite(v) for v in summary.after.values())
    assert all(torch.isfinite(p).all() for p in model.parameters())
