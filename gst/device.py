"""Where the network runs: the `device` setting of training and tracking, and moving batches.

`device: auto` (the default of the pipeline's stages) is the first CUDA device when PyTorch sees
one and the CPU otherwise, so a GPU user gets the GPU without editing `pipeline.yaml` and a CPU
machine never asks for one. Crop stores, samplers and random generators stay on the CPU (their
draws are then identical on every device); each batch moves to the network's device just before
its step (`move_to`).
"""

from __future__ import annotations

import copy
import dataclasses
import os
from typing import TypeVar

import torch

__all__ = ["check_device_name", "resolve_device", "model_device", "module_on", "move_to"]

T = TypeVar("T")
M = TypeVar("M", bound=torch.nn.Module)


def check_device_name(spec: str) -> str:
    """`spec` as it is when it names a device (auto, cpu, cuda, cuda:N, ...), else a ValueError
    saying what is expected: for settings, checked before any stage runs (`tpu` failed in the
    stage, after the ones before it). Whether a CUDA device is there is `resolve_device`'s
    question, asked where the stage runs."""
    if isinstance(spec, str) and spec.strip().lower() == "auto":
        return spec
    try:
        torch.device(spec.strip().lower())
    except (RuntimeError, ValueError, AttributeError) as err:
        raise ValueError(
            f"device '{spec}' is not a device (expected auto, cpu, cuda or cuda:N)"
        ) from err
    return spec


def resolve_device(spec: str | torch.device | None = "auto") -> torch.device:
    """'auto' (or None): cuda when available, else cpu; 'cpu', 'cuda', 'cuda:N' as named. A CUDA
    device that is not there is an error that says what is, never a silent CPU run. Under
    torchrun (LOCAL_RANK set) a bare 'cuda' is the rank's own GPU."""
    if spec is None or (isinstance(spec, str) and spec.strip().lower() == "auto"):
        spec = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(spec.strip().lower() if isinstance(spec, str) else spec)
    except (RuntimeError, ValueError) as err:
        raise ValueError(
            f"device '{spec}' is not a device (expected auto, cpu, cuda or cuda:N)"
        ) from err
    if device.type == "cuda" and device.index is None and "LOCAL_RANK" in os.environ:
        device = torch.device("cuda", int(os.environ["LOCAL_RANK"]))
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"device '{spec}' asked for, but PyTorch sees no CUDA device (torch "
                f"{torch.__version__}, CUDA build {torch.version.cuda}); use device: auto or cpu"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(
                f"device '{spec}' asked for, but only {torch.cuda.device_count()} CUDA device(s) "
                "are visible"
            )
    elif device.type != "cpu":
        raise ValueError(f"device '{spec}' is not supported (expected auto, cpu, cuda or cuda:N)")
    return device


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of a module's first parameter (or buffer); the CPU for an empty module."""
    for tensor in model.parameters():
        return tensor.device
    for tensor in model.buffers():
        return tensor.device
    return torch.device("cpu")


def module_on(module: M, device: torch.device | str) -> M:
    """`module` itself when it already lives on `device`, else a copy moved there: modules move in
    place, and a body model shared with a CPU sampler must stay where that sampler needs it."""
    if model_device(module) == torch.device(device):
        return module
    return copy.deepcopy(module).to(device)


def move_to(obj: T, device: torch.device | str) -> T:
    """`obj` with every tensor inside it on `device`: tensors, dataclasses (a new instance of the
    same class; frozen ones too), dicts, lists and tuples, recursively; objects with their own
    `to(device)` that are not modules (e.g. `LandmarkInput`) use it; anything else is returned
    as is. Tensors already there are not copied."""
    if isinstance(obj, torch.Tensor):
        # asynchronous copies only towards a GPU: a GPU -> CPU copy must be complete when read
        return obj.to(device, non_blocking=torch.device(device).type == "cuda")
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        if hasattr(obj, "to") and not isinstance(obj, torch.nn.Module):
            return obj.to(device)
        changes = {
            f.name: move_to(getattr(obj, f.name), device) for f in dataclasses.fields(obj) if f.init
        }
        return dataclasses.replace(obj, **changes)
    if isinstance(obj, dict):
        return type(obj)((k, move_to(v, device)) for k, v in obj.items())
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):  # named tuple
        return type(obj)(*(move_to(v, device) for v in obj))
    if isinstance(obj, (list, tuple)):
        return type(obj)(move_to(v, device) for v in obj)
    return obj
