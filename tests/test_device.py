"""gst.device and training on a chosen device.

Moving is checked on PyTorch's `meta` device (a second device every machine has), so the CPU
suite tests it; the CUDA tests (marked `cuda`) train and validate on the GPU where there is one
and compare with the same run on the CPU.
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from gst.device import model_device, module_on, move_to, resolve_device
from gst.model.checkpoint import load_checkpoint
from gst.model.inference import GSTPredictor
from tests.test_train_recipe import crop_set, small_fit

HAS_CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")


@dataclass(frozen=True)
class _Frozen:
    a: torch.Tensor
    b: list
    name: str = "x"


@dataclass
class _Outer:
    inner: _Frozen
    table: dict
    n: int


Pair = namedtuple("Pair", "x y")


def test_auto_is_cuda_exactly_when_pytorch_sees_it():
    assert resolve_device("auto").type == ("cuda" if HAS_CUDA else "cpu")
    assert resolve_device(None) == resolve_device("auto")
    assert resolve_device(" CPU ") == torch.device("cpu")


@pytest.mark.parametrize("bad", ["tpu", "gpu0", "mps"])
def test_unknown_devices_are_refused_with_the_choices(bad):
    with pytest.raises(ValueError, match="auto, cpu, cuda"):
        resolve_device(bad)


def test_cuda_without_cuda_says_so():
    if HAS_CUDA:
        with pytest.raises(ValueError, match="CUDA device"):
            resolve_device(f"cuda:{torch.cuda.device_count()}")
    else:
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")


def test_move_to_reaches_every_tensor_and_keeps_the_rest():
    t = torch.arange(3.0)
    obj = _Outer(
        inner=_Frozen(a=t, b=[t, (t, 1)], name="kept"),
        table={"k": t, "p": Pair(t, "s")},
        n=4,
    )
    moved = move_to(obj, "meta")
    assert isinstance(moved, _Outer) and isinstance(moved.inner, _Frozen)
    tensors = [
        moved.inner.a, moved.inner.b[0], moved.inner.b[1][0], moved.table["k"], moved.table["p"].x
    ]  # fmt: skip
    assert all(x.device.type == "meta" and x.shape == (3,) for x in tensors)
    assert isinstance(moved.table["p"], Pair) and moved.table["p"].y == "s"
    assert moved.inner.name == "kept" and moved.n == 4 and moved.inner.b[1][1] == 1
    assert obj.inner.a.device.type == "cpu"  # the original is untouched
    same = move_to(obj, "cpu")
    assert same.inner.a is t  # already there: no copy


def test_module_on_copies_only_when_it_must():
    lin = torch.nn.Linear(2, 2)
    assert module_on(lin, "cpu") is lin
    moved = module_on(lin, "meta")
    assert moved is not lin and model_device(moved).type == "meta"
    assert model_device(lin).type == "cpu"
    assert model_device(torch.nn.Module()) == torch.device("cpu")


def test_cpu_training_writes_cpu_checkpoints_and_keeps_the_callers_body(tmp_path):
    net, body, summary = small_fit(tmp_path, device="cpu", steps=2)
    assert summary.steps == 2 and model_device(net).type == "cpu"
    ckpt = load_checkpoint(tmp_path / "last.pt")
    assert all(v.device.type == "cpu" for v in ckpt.model.values())


@pytest.mark.cuda
@needs_cuda
@pytest.mark.parametrize("mode", ["multiview", "pretrain"])
def test_cuda_training_matches_the_cpu_before_the_first_step(tmp_path, mode):
    """Same seed, same batches (drawn on the CPU): validation before training agrees between
    the devices; training runs, stays finite, and writes CPU checkpoints."""
    _, _, cpu = small_fit(tmp_path / "cpu", mode, device="cpu", steps=3)
    net, body, gpu = small_fit(tmp_path / "cuda", mode, device="cuda", steps=3)
    assert model_device(net).type == "cuda"
    assert model_device(body).type == "cpu"  # the task got a copy; the caller's body stays
    for key, value in cpu.before.items():
        assert math.isclose(gpu.before[key], value, rel_tol=2e-3, abs_tol=1e-3), key
    assert gpu.steps == 3 and gpu.bad_steps == 0
    assert all(math.isfinite(v) for v in gpu.after.values())
    ckpt = load_checkpoint(tmp_path / "cuda" / "last.pt")
    assert all(v.device.type == "cpu" for v in ckpt.model.values())


@pytest.mark.cuda
@needs_cuda
def test_cuda_training_with_rehearsal_and_resume(tmp_path):
    """The landmark prior rehearsed on the GPU while its sampler stays on the CPU, and a run
    resumed on the GPU from a GPU run's checkpoint."""
    net, body, first = small_fit(tmp_path, device="cuda", rehearse=True, steps=2)
    assert first.steps == 2 and first.bad_steps == 0
    _, _, resumed = small_fit(tmp_path, device="cuda", rehearse=True, steps=4)
    assert resumed.steps == 4 and all(math.isfinite(v) for v in resumed.after.values())


@pytest.mark.cuda
@needs_cuda
def test_a_gpu_predictor_gives_the_cpu_predictors_bodies(tmp_path):
    """What `track` runs with device: cuda (GSTPredictor built on the CPU, then moved) against
    the same checkpoint on the CPU, on the same crops and landmarks."""
    small_fit(tmp_path, device="cuda", rehearse=True, steps=1)
    crops = crop_set()
    lm = torch.rand(len(crops), 33, 3) * torch.tensor([64.0, 64.0, 1.0])
    out = {
        device: GSTPredictor(tmp_path / "last.pt", device=device)(
            crops.images.numpy(), crops.K.numpy(), landmarks=lm.numpy()
        )
        for device in ("cpu", "cuda")
    }
    for key in ("joints_cam", "transl_cam", "rotmats"):
        np.testing.assert_allclose(out["cuda"][key], out["cpu"][key], atol=2e-3, err_msg=key)


@pytest.mark.skipif(HAS_CUDA, reason="checks a machine without CUDA")
def test_stages_refuse_a_missing_gpu_before_any_work(tmp_path):
    """`device: cuda` on a machine without CUDA fails at once, naming the setting's values,
    before crops load or worlds render (the inputs here do not even exist)."""
    from gst.lift.recipe import pretrain
    from gst.train.pretrain import PretrainConfig
    from gst.train.scene_training import TrainSettings, train_scene

    with pytest.raises(ValueError, match="no CUDA device.*auto or cpu"):
        train_scene(TrainSettings(device="cuda"), tmp_path / "no.h5", tmp_path / "no.pt", None)
    with pytest.raises(ValueError, match="no CUDA device"):
        pretrain(PretrainConfig(device="cuda"), tmp_path, tmp_path / "p.pt", tmp_path / "r")
    assert not any(tmp_path.iterdir())  # nothing was written
