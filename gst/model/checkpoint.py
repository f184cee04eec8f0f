"""GST checkpoints: plain dicts of tensors and primitives, safe to load with weights_only=True.

Layout (`torch.save` of a dict):
    format: "gst-capture/checkpoint", version: 1
    config: GSTConfig as nested dicts
    body_model: body spec string ("anny" or a path to the user's SMPL file)
    vertex_ids: LongTensor (V,)   group_index: LongTensor (V,)
    model: network state_dict
    extra: dict of primitives about the training (`gst.train.recipe`: mode, heldout_cameras,
        first_heldout_frame, trained_on)
    trainer: the training loop's state (step, optimiser, scheduler, random streams;
        `gst.train.trainer`), only in checkpoints written during training: `keep_model` drops
        it from the kept models (`models/*.pt`)
Writes go to a temporary file that is renamed, so a killed save never leaves a truncated file.
`load_checkpoint` checks a file and returns its fields as a `GSTCheckpoint`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from gst.atomic import atomic_torch_save
from gst.model.decoder import DecoderConfig
from gst.model.network import GSTNetwork
from gst.model.presets import GSTConfig
from gst.model.refine import ReprojectionRefiner
from gst.model.vit import ViTConfig

FORMAT, VERSION = "gst-capture/checkpoint", 1


def config_to_dict(cfg: GSTConfig) -> dict:
    return dataclasses.asdict(cfg)


def config_from_dict(d: dict) -> GSTConfig:
    for key in ("vit", "decoder"):  # named here: a bare KeyError said only 'decoder'
        if not isinstance(d.get(key), dict):
            got = "nothing" if key not in d else type(d[key]).__name__
            raise ValueError(f"config lacks '{key}' (a dict of its settings; got {got})")
    vit = dict(d["vit"])
    vit["image_size"] = tuple(vit["image_size"])
    return GSTConfig(**{**d, "vit": ViTConfig(**vit), "decoder": DecoderConfig(**d["decoder"])})


def save_checkpoint(
    path: str | Path,
    network: GSTNetwork,
    body_spec: str,
    vertex_ids: np.ndarray,
    group_index: np.ndarray,
    extra: dict | None = None,
) -> None:
    atomic_torch_save(
        {
            "format": FORMAT,
            "version": VERSION,
            "config": config_to_dict(network.cfg),
            "body_model": body_spec,
            "vertex_ids": torch.as_tensor(np.asarray(vertex_ids), dtype=torch.long),
            "group_index": torch.as_tensor(np.asarray(group_index), dtype=torch.long),
            "model": network.state_dict(),
            "extra": extra or {},
        },
        path,
    )


@dataclasses.dataclass(frozen=True, eq=False)
class GSTCheckpoint:
    """A checkpoint as `load_checkpoint` reads it (the file's layout: module doc). `trainer`:
    the training loop's state in checkpoints written during training (`gst.train.trainer`),
    None in the kept models."""

    config: dict
    body_model: str
    vertex_ids: torch.Tensor
    group_index: torch.Tensor
    model: dict[str, torch.Tensor]
    extra: dict = dataclasses.field(default_factory=dict)
    trainer: dict | None = None


_REQUIRED = ("config", "body_model", "vertex_ids", "group_index", "model")


def keep_model(source: str | Path, dest: str | Path) -> None:
    """Write a training checkpoint as a kept model (`models/*.pt`): everything but the training
    loop's state (`trainer`: the optimiser's moments, twice the weights' size, which only a
    resumed run reads)."""
    ckpt = _read_checked(Path(source), "cpu")  # the same checks as any reader's
    ckpt.pop("trainer", None)
    atomic_torch_save(ckpt, dest)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> GSTCheckpoint:
    """Read and check a checkpoint (weights_only=True: no code runs while loading)."""
    ckpt = _read_checked(Path(path), map_location)
    return GSTCheckpoint(
        config=ckpt["config"],
        body_model=ckpt["body_model"],
        vertex_ids=ckpt["vertex_ids"],
        group_index=ckpt["group_index"],
        model=ckpt["model"],
        extra=ckpt.get("extra") or {},
        trainer=ckpt.get("trainer"),
    )


def load_refusal(exc: Exception) -> str:
    """What torch.load refused, in one line: for a pickle that weights_only=True will not run,
    the object it refused ("Unsupported global: GLOBAL posix.system"), not torch's first line,
    which ends advising weights_only=False, unsafe for a file one does not trust."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    why = next((line for line in lines if "unsupported" in line.lower()), None)
    if why is None:
        why = lines[0] if lines else ""
        if "weights_only" in why:  # the unsafe advice, with no reason given
            why = "the file holds pickled objects that a safe load does not run"
    return f"{type(exc).__name__}: {why[:200]}"


def _read_checked(path: Path, map_location: str | torch.device) -> dict:
    """The checkpoint file's dict, read with weights_only=True and checked (format, version,
    keys, one vertex id per Gaussian); a ValueError naming the file otherwise."""
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # truncated, not a torch file, or pickled code weights_only refuses
        raise ValueError(
            f"{path}: cannot be read as a GST checkpoint ({load_refusal(exc)}); "
            "expected a file written by the pretrain or train stage"
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{path}: not a GST checkpoint (expected format '{FORMAT}')")
    if ckpt.get("version") != VERSION:
        raise ValueError(
            f"{path}: checkpoint version {ckpt.get('version')} is not supported "
            f"(expected {VERSION})"
        )
    missing = [k for k in _REQUIRED if k not in ckpt]
    if missing:
        raise ValueError(f"{path}: a GST checkpoint without {missing}")
    ids, groups = ckpt["vertex_ids"], ckpt["group_index"]
    if not all(
        isinstance(t, torch.Tensor) and t.ndim == 1 and not t.dtype.is_floating_point
        for t in (ids, groups)
    ) or len(ids) != len(groups):
        # one vertex id for 1723 Gaussians put them all on one vertex, silently
        shapes = [tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                  for t in (ids, groups)]  # fmt: skip
        raise ValueError(
            f"{path}: vertex_ids and group_index must be 1-D integer tensors of one length (one "
            f"per Gaussian), got {shapes[0]} and {shapes[1]}"
        )
    if len(ids) and int(ids.min()) < 0:
        raise ValueError(
            f"{path}: vertex_ids must be body-model vertex indices, got {int(ids.min())}"
        )
    for key in ("config", "model", "extra"):  # their readers call .get and .items on them
        value = ckpt.get(key)
        if not isinstance(value, dict) and not (key == "extra" and value is None):
            raise ValueError(f"{path}: '{key}' must be a dict, got {type(value).__name__}")
    if not isinstance(ckpt["body_model"], str):
        raise ValueError(
            f"{path}: body_model must name a body model (text), got "
            f"{type(ckpt['body_model']).__name__}"
        )
    return ckpt


def network_from_checkpoint(ckpt: GSTCheckpoint, source: str | Path | None = None) -> GSTNetwork:
    """The network a checkpoint holds; `source` names the file in errors (weights that do not
    fit the network, or that are not finite)."""
    where = f"{source}: " if source is not None else ""
    try:  # the config apart from the weights: its faults were blamed on the weights
        cfg = config_from_dict(ckpt.config)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f"{where}the checkpoint's config does not describe a GST network ({exc})"
        ) from None
    try:
        net = GSTNetwork(cfg, ckpt.group_index.numpy())
        net.load_state_dict(ckpt.model)
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise ValueError(
            f"{where}the checkpoint's weights do not fit its network ({exc})"
        ) from None
    bad = _first_non_finite(net)
    if bad is not None:
        # a diverged run or a damaged file: it failed later, at the first batch, naming no file
        key, t = bad
        raise ValueError(
            f"{where}the checkpoint's weight '{key}' is not finite ({int(t.isnan().sum())} NaN, "
            f"{int(t.isinf().sum())} infinite of {t.numel()} values): the file is damaged or "
            "its training diverged; use another checkpoint or train again"
        )
    return net


def _first_non_finite(net: GSTNetwork) -> tuple[str, torch.Tensor] | None:
    """The first floating-point weight or buffer of `net` holding NaN or infinity, with its
    key; None when all are finite. The refiner's body buffers are NaN by design until
    `set_body` runs (`ReprojectionRefiner.BODY_BUFFERS`): left out."""
    unset = {
        f"{name}.{buf}"
        for name, module in net.named_modules()
        if isinstance(module, ReprojectionRefiner)
        for buf in module.BODY_BUFFERS
    }
    return first_non_finite(net.state_dict(), skip=unset)


def first_non_finite(
    state: dict[str, torch.Tensor], skip: set[str] | frozenset[str] = frozenset()
) -> tuple[str, torch.Tensor] | None:
    """The first floating-point tensor of `state` (keys in `skip` left out) holding NaN or
    infinity, with its key; None when all are finite."""
    for key, t in state.items():
        if key in skip or not t.dtype.is_floating_point:
            continue
        if not bool(torch.isfinite(t).all()):
            return key, t
    return None
