"""Import an HMR2 (4D-Humans) checkpoint into a GST network built with the `huge` preset.

HMR2's keys `backbone.*` (ViTPose-H) and `smpl_head.*` (cross-attention SMPL head, its linear
decoders and the mean-parameter buffers) map one to one onto ours; GST's Gaussian tokens and
heads have no HMR2 counterpart and keep their initialisation. Everything else in the
checkpoint (the SMPL layer, the discriminator, ...) is reported as unmatched.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from gst.model.checkpoint import first_non_finite, load_refusal

_PREFIXES = ("backbone.", "smpl_head.")


@dataclass
class ImportReport:
    loaded: list[str] = field(default_factory=list)
    unmatched_checkpoint_keys: list[str] = field(default_factory=list)  # in the file, not used
    missing_model_keys: list[str] = field(default_factory=list)  # in the model, not in the file
    shape_mismatches: list[str] = field(default_factory=list)

    def summary(self) -> str:
        return (
            f"loaded {len(self.loaded)} tensors; "
            f"{len(self.unmatched_checkpoint_keys)} checkpoint keys unused; "
            f"{len(self.missing_model_keys)} model keys kept at init; "
            f"{len(self.shape_mismatches)} shape mismatches"
        )


def read_checkpoint_state(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a checkpoint, loaded with weights_only=True (Lightning's `state_dict` entry
    when present). Checkpoints holding arbitrary pickled objects are refused, not executed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"HMR2 checkpoint not found: {path}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # refused pickled objects, or not a (whole) torch file at all
        why = load_refusal(exc)
        if isinstance(exc, pickle.UnpicklingError) and "unsupported global" in str(exc).lower():
            # a pickled Python object (yacs' CfgNode in HMR2's own files): the advice to re-save
            # its tensors is for that alone, not for a file that is no pickle at all
            raise ValueError(
                f"{path}: cannot be loaded with weights_only=True ({why}). It pickles Python "
                "objects besides tensors; in a trusted environment re-save just its tensors: "
                "torch.save(torch.load(p, weights_only=False)['state_dict'], 'hmr2_state.pt')"
            ) from None
        text = why
        # an empty file (EOFError), a text file (KeyError), a cut download (RuntimeError):
        # advice to unpickle it without weights_only would be wrong and unsafe
        raise ValueError(
            f"{path}: cannot be read as a torch checkpoint ({type(exc).__name__}: {text}); is "
            "the file whole (compare its size with the download's)?"
        ) from None
    state = obj.get("state_dict", obj) if isinstance(obj, dict) else None
    if not isinstance(state, dict):
        raise ValueError(
            f"{path}: expected a dict of tensors (or a dict with 'state_dict'), "
            f"got {type(obj).__name__}"
        )
    return {k: v for k, v in state.items() if isinstance(v, torch.Tensor)}


def import_hmr2(
    network: nn.Module, source: str | Path | dict[str, torch.Tensor], strict_shapes: bool = True
) -> ImportReport:
    """Copy HMR2 weights into `network` (a GSTNetwork) in place and report what matched."""
    state = read_checkpoint_state(source) if not isinstance(source, dict) else source
    own = network.state_dict()
    report = ImportReport()
    updates = {}
    for key, value in state.items():
        if not key.startswith(_PREFIXES) or key not in own:
            report.unmatched_checkpoint_keys.append(key)
            continue
        if tuple(own[key].shape) != tuple(value.shape):
            report.shape_mismatches.append(
                f"{key}: checkpoint {tuple(value.shape)} vs model {tuple(own[key].shape)}"
            )
            continue
        updates[key] = value.to(own[key].dtype)
        report.loaded.append(key)
    if report.shape_mismatches and strict_shapes:
        raise ValueError(
            "HMR2 import: shapes differ (is the network built with the 'huge' preset?):\n  "
            + "\n  ".join(report.shape_mismatches[:20])
        )
    report.missing_model_keys = [k for k in own if k not in updates]
    # An import that fills neither the whole ViT nor any of the SMPL head is a wrong file (a
    # ViTPose checkpoint, keys under another prefix): training would start from random weights.
    backbone_missing = [k for k in report.missing_model_keys if k.startswith("backbone.")]
    head_loaded = any(k.startswith("smpl_head.") for k in report.loaded)
    if backbone_missing or not head_loaded:
        name = "the given state dict" if isinstance(source, dict) else str(source)
        raise ValueError(
            f"HMR2 import from {name}: {len(report.loaded)} tensors matched; "
            f"{len(backbone_missing)} of the ViT's (backbone.*) are missing"
            + ("" if head_loaded else " and none of the SMPL head's (smpl_head.*) loaded")
            + f". Keys in the file look like {report.unmatched_checkpoint_keys[:3]}: HMR2's are "
            "backbone.* and smpl_head.* (strip another prefix, e.g. 'model.', before importing)"
        )
    bad = first_non_finite(updates)  # as GST checkpoints are checked (network_from_checkpoint)
    if bad is not None:
        key, t = bad
        name = "the given state dict" if isinstance(source, dict) else str(source)
        raise ValueError(
            f"HMR2 import from {name}: the weight '{key}' is not finite "
            f"({int(t.isnan().sum())} NaN, {int(t.isinf().sum())} infinite of {t.numel()} "
            "values): the file is damaged; download it again"
        )
    network.load_state_dict(updates, strict=False)
    return report
