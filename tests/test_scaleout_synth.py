"""synth fanned out over camera shares: serial, 2 local worker processes and a 2-worker Ray
cluster write byte-identical scene folders (scene.json has no timing fields, so every file is
compared), and a failing share leaves no partial folder."""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

import pytest
from synth_fixtures import CapsuleBody, rig_io, small_scene_spec

from pipeline.executors import LocalExecutor
from synth.scene import render_scene
from synth.shares import camera_shares

BODY = CapsuleBody()
WRITE_RIG, _ = rig_io()
HAVE_RAY = importlib.util.find_spec("ray") is not None


def _spec():
    return small_scene_spec(
        n_frames=5,
        rig=dict(n_cameras=3, width=80, height=60, distortion="mild"),
        board=dict(n_frames=2),
        imaging=dict(shadow_samples=2),
    )


def _render(out: Path, **kwargs):
    """render_scene of the test spec into `out`, capsule body and the project's rig writer."""
    return render_scene(_spec(), out, body_model=BODY, rig_writer=WRITE_RIG, **kwargs)


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


class _RecordingMap:
    """A map_fn that runs inline and records what it was given (items must survive pickling)."""

    def __init__(self):
        self.calls = []

    def __call__(self, fn, items, description=""):
        import pickle

        items = [pickle.loads(pickle.dumps(x)) for x in items]
        self.calls.append((fn.__module__, fn.__name__, len(items), description))
        return [pickle.loads(pickle.dumps(fn(x))) for x in items]


@pytest.fixture(scope="module")
def serial_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "scene"
    summary = _render(out)
    return out, summary


def test_camera_shares_split_groups_in_order():
    assert camera_shares([[0, 1, 2], [3, 4]], None) == [(0, 1, 2), (3, 4)]
    assert camera_shares([[0, 1, 2, 3, 4, 5]], 2) == [(0, 1, 2), (3, 4, 5)]
    assert camera_shares([[0, 1, 2, 3, 4, 5, 6]], 2) == [(0, 1, 2, 3), (4, 5, 6)]
    assert camera_shares([[0, 1, 2], [3, 4]], 2) == [(0, 1, 2), (3, 4)]
    assert camera_shares([[0, 1, 2], [3, 4]], 5) == [(0,), (1,), (2,), (3,), (4,)]
    assert camera_shares([[0, 1]], 8) == [(0,), (1,)]
    with pytest.raises(ValueError, match="n_shares"):
        camera_shares([[0]], 0)


@pytest.mark.parametrize("n_shares", [3, 2, None])
def test_pickled_shares_give_identical_files(serial_scene, tmp_path, n_shares):
    out, summary = serial_scene
    mapper = _RecordingMap()
    fanned = _render(tmp_path / "scene", map_fn=mapper, shares=n_shares)
    assert mapper.calls == [
        ("synth.shares", "render_share_job", n_shares or 1, "synth demo: render")
    ]
    assert _digest(tmp_path / "scene") == _digest(out)
    assert not (tmp_path / "scene" / ".cast").exists()
    assert (fanned.joints_in_mask, fanned.joints_on_own_mask) == (
        summary.joints_in_mask,
        summary.joints_on_own_mask,
    )


def test_two_local_worker_processes_give_identical_files(serial_scene, tmp_path):
    out, _ = serial_scene
    _render(tmp_path / "scene", map_fn=LocalExecutor(2).map, shares=2)
    assert _digest(tmp_path / "scene") == _digest(out)


def _failing_map(fn, items, description=""):
    results = [fn(x) for x in list(items)[:-1]]  # earlier shares write their files, then one fails
    raise RuntimeError("worker lost")
    return results


def test_failed_share_leaves_previous_scene_untouched(serial_scene, tmp_path):
    out, _ = serial_scene
    target = tmp_path / "scene"
    _render(target)
    before = _digest(target)
    with pytest.raises(RuntimeError, match="worker lost"):
        _render(target, map_fn=_failing_map, shares=3)
    assert _digest(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no staging folder left behind


def test_map_fn_that_drops_a_share_is_an_error(tmp_path):
    with pytest.raises(RuntimeError, match="3 camera shares"):
        _render(
            tmp_path / "scene",
            shares=3,
            map_fn=lambda fn, items, description="": [fn(x) for x in list(items)[:2]],
        )
    assert not (tmp_path / "scene").exists()


@pytest.fixture(scope="module")
def ray_executor():
    if not HAVE_RAY:
        pytest.skip("ray is not installed: pip install -e '.[dist]' to run the Ray synth tests")
    from pipeline.ray_executor import RayExecutor

    with RayExecutor(2) as ex:
        yield ex


def test_two_worker_ray_cluster_gives_identical_files(serial_scene, ray_executor, tmp_path):
    out, _ = serial_scene
    _render(tmp_path / "scene", map_fn=ray_executor.map, shares=2)
    assert _digest(tmp_path / "scene") == _digest(out)


def test_worker_killed_mid_share_is_retried_with_identical_files(
    serial_scene, ray_executor, tmp_path
):
    from tests.scaleout_synth_items import DieOnceMidShare

    out, _ = serial_scene
    (tmp_path / "markers").mkdir()

    def dying_map(fn, items, description=""):
        return ray_executor.map(
            DieOnceMidShare(fn, tmp_path / "markers", camera=0), items, description
        )

    _render(tmp_path / "scene", map_fn=dying_map, shares=2)
    assert (tmp_path / "markers" / "died-0").exists()  # the worker did die once
    assert _digest(tmp_path / "scene") == _digest(out)  # and the stale half-written video is gone
