"""The Ray executor against the local one: same results for extract and track, retries after a
killed worker with nothing lost or duplicated. One local 2-worker cluster serves the module."""

from __future__ import annotations

import functools

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest

ray = pytest.importorskip(
    "ray", reason="ray is not installed: pip install -e '.[dist]' to run the Ray executor tests"
)

from gst.data import extract_scene  # noqa: E402
from gst.track.batch import track_videos  # noqa: E402
from gst.track.chunks import ChunkingConfig  # noqa: E402
from pipeline.executors import LocalExecutor, make_executor  # noqa: E402
from pipeline.ray_executor import ItemFailed, RayExecutor  # noqa: E402
from tests.extract_scenes import make_short_scene  # noqa: E402
from tests.scaleout_items import KillOnceDetector, MarkedItem, always_fails, square_and_record  # noqa: E402
from tests.scaleout_scenes import job, write_clip  # noqa: E402
from tests.test_extract_scene import _opts  # noqa: E402


@pytest.fixture(scope="module")
def ray_executor():
    seen = []

    def progress(items, description="", total=None):
        for x in items:
            seen.append((description, total))
            yield x

    ex = RayExecutor(2, progress)
    ex.progress_seen = seen
    yield ex
    ex.shutdown()
    assert not ray.is_initialized()


@pytest.fixture(scope="module")
def local_executor():
    return LocalExecutor(2)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    d = tmp_path_factory.mktemp("clips")
    return [write_clip(d, "long", 60), write_clip(d, "short", 30)]


def test_make_executor_builds_ray():
    ex = make_executor("ray", 2)
    assert isinstance(ex, RayExecutor) and ex.workers == 2


def test_ordered_results_progress_and_workers_import_this_checkout(ray_executor, tmp_path):
    items = [MarkedItem(i, tmp_path) for i in range(7)]
    assert ray_executor.map(square_and_record, items, "squares") == [i * i for i in range(7)]
    assert [d for d in ray_executor.progress_seen if d[0] == "squares"] == [("squares", 7)] * 7
    import pipeline

    def where(_):
        import pipeline as p

        return p.__file__

    assert set(ray_executor.map(where, range(2))) == {pipeline.__file__}


@pytest.mark.parametrize("crash", ["kill", "raise"])
def test_failed_item_is_retried_nothing_lost_or_duplicated(ray_executor, tmp_path, crash):
    items = [MarkedItem(i, tmp_path, crash if i == 3 else "") for i in range(6)]
    assert ray_executor.map(square_and_record, items, "crashy") == [i * i for i in range(6)]
    for i in range(6):  # every item completed exactly once
        assert (tmp_path / f"log-{i}.txt").read_text() == f"{i}\n"


def test_persistent_failure_names_the_item(ray_executor):
    with pytest.raises(
        ItemFailed, match=r"bad: item 0 \(12\) failed after 2 attempt\(s\): ValueError: bad item 12"
    ):
        ray_executor.map(always_fails, [12], "bad")
    with pytest.raises(ItemFailed, match=r"item [01] \(1[12]\) failed after 2"):
        ray_executor.map(always_fails, [11, 12], "bad")


def _rows(path):
    return pq.read_table(path).replace_schema_metadata(None)


def test_track_ray_equals_local(ray_executor, local_executor, clips, tmp_path):
    jobs = [job(v, c) for v, c in clips]
    chunking = ChunkingConfig(chunk_frames=20, overlap=5)
    local = track_videos(jobs, tmp_path / "local", map_fn=local_executor.map, chunking=chunking)
    remote = track_videos(jobs, tmp_path / "ray", map_fn=ray_executor.map, chunking=chunking)
    serial = track_videos(jobs, tmp_path / "serial")  # unchunked, in this process
    assert [o.chunks for o in remote] == [3, 2]
    for a, b, c in zip(local, remote, serial, strict=True):
        assert pq.read_table(a.result.path).equals(pq.read_table(b.result.path))  # metadata too
        assert _rows(b.result.path).equals(_rows(c.result.path))


@pytest.mark.parametrize("chunked", [False, True])
def test_track_worker_killed_mid_video_is_resumed_exactly(ray_executor, clips, tmp_path, chunked):
    video, csv = clips[0]
    killer = functools.partial(KillOnceDetector, csv, video.stem, tmp_path / "killed", 33)
    chunking = ChunkingConfig(chunk_frames=20, overlap=5) if chunked else None
    out = track_videos(
        [job(video, csv, detector=killer)],
        tmp_path / "out",
        map_fn=ray_executor.map,
        chunking=chunking,
    )[0]
    assert (tmp_path / "killed").exists()  # the worker really died once
    if not chunked:
        # The retry continued after the last committed group (detection runs a few frames ahead).
        assert out.result.resumed_from_frame in (20, 25, 30)
    reference = track_videos([job(video, csv)], tmp_path / "ref")[0]
    assert _rows(out.result.path).equals(
        _rows(reference.result.path)
    )  # nothing lost, nothing twice


def _h5_contents(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda name, obj: (
                out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None
            )
        )
    return out


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return make_short_scene(tmp_path_factory.mktemp("extract"))


def test_extract_ray_equals_local(ray_executor, local_executor, small_scene, tmp_path):
    def run(name, map_fn):
        out = tmp_path / name / "crops.h5"
        rep = extract_scene(
            small_scene.videos,
            small_scene.rig,
            out,
            crop_size=64,
            options=_opts(),
            executor_map=map_fn,
        )
        return rep, _h5_contents(out)

    rep_local, local = run("local", local_executor.map)
    rep_ray, remote = run("ray", ray_executor.map)
    assert rep_local.crops == rep_ray.crops > 0
    assert local.keys() == remote.keys()
    for k in local:
        np.testing.assert_array_equal(local[k], remote[k], err_msg=k)
