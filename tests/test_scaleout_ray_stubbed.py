"""The Ray executor's bookkeeping against a stand-in `ray` module (runs without the 'dist'
extra; tests/test_scaleout_ray.py runs a real cluster)."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


class _RayError(Exception):
    pass


class _RayTaskError(_RayError):
    pass


def _stub_ray(wait):
    """A `ray` whose tasks never finish: `wait` decides what waiting for them does."""
    ray = types.ModuleType("ray")
    ray.submitted, ray.cancelled = [], []

    def remote(**_):
        def wrap(fn):
            def submit(*args):
                ref = object()
                ray.submitted.append(ref)
                return ref

            return types.SimpleNamespace(remote=submit)

        return wrap

    ray.is_initialized = lambda: True
    ray.remote = remote
    ray.put = lambda value: value
    ray.wait = wait
    ray.cancel = lambda ref, force=False: ray.cancelled.append(ref)
    exceptions = types.ModuleType("ray.exceptions")
    exceptions.RayError, exceptions.RayTaskError = _RayError, _RayTaskError
    ray.exceptions = exceptions
    return ray, exceptions


def _ray_executor_module(monkeypatch, ray, exceptions):
    monkeypatch.setitem(sys.modules, "ray", ray)
    monkeypatch.setitem(sys.modules, "ray.exceptions", exceptions)
    spec = importlib.util.spec_from_file_location(
        "_ray_executor_stubbed", REPO / "pipeline" / "ray_executor.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ctrl_c_during_a_ray_map_cancels_the_pending_tasks(monkeypatch):
    """A Ctrl-C while the map waited left every task running: on a cluster given with
    --ray-address they went on writing into the staging folder the next run uses."""

    def interrupted(refs, num_returns=1):
        raise KeyboardInterrupt

    ray, exceptions = _stub_ray(interrupted)
    module = _ray_executor_module(monkeypatch, ray, exceptions)
    with pytest.raises(KeyboardInterrupt):
        module.RayExecutor(2, address="auto").map(str, range(4), "squares")
    assert len(ray.submitted) == 4
    assert sorted(map(id, ray.cancelled)) == sorted(map(id, ray.submitted))
