"""How `track` shares the cores between the person model's LiteRT threads and the network's
torch threads, and that a job's torch threads do not leak into the caller's process."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.track import batch
from gst.track.scene import (
    TrackSettings,
    detector_interval,
    jobs_at_once,
    network_threads,
    person_model_config,
)


@pytest.fixture
def cores(monkeypatch):
    def set_cores(n: int) -> None:
        monkeypatch.setattr("gst.track.scene.available_cores", lambda: n)

    return set_cores


def test_network_gets_the_cores_the_person_model_leaves(cores):
    cores(2)
    s = TrackSettings()
    assert person_model_config(s).threads == 2
    assert network_threads(s, "blazepose", workers=1, parallel_videos=1) == 1
    cores(16)
    assert person_model_config(s).threads == 4  # LiteRT is capped at 4
    assert network_threads(s, "blazepose", workers=1, parallel_videos=1) == 12
    # two videos at once on 16 cores: 8 each, 4 of them to LiteRT
    assert network_threads(s, "blazepose", workers=1, parallel_videos=2) == 4
    cores(1)
    assert network_threads(s, "blazepose", workers=1, parallel_videos=1) == 1


def test_explicit_settings_and_other_detectors(cores):
    cores(2)
    assert network_threads(TrackSettings(threads=3), "blazepose", 1, 1) == 3
    assert network_threads(TrackSettings(), "blazepose", workers=2, parallel_videos=2) == 1
    # without the person model's thread, torch keeps its own pool
    assert network_threads(TrackSettings(), "background", 1, 1) is None
    assert network_threads(TrackSettings(), "boxes", 1, 1) is None
    s = TrackSettings(detector_threads=1)
    assert network_threads(s, "blazepose", 1, 1) == 1  # 2 cores - 1 LiteRT thread
    # the person model's other settings reach it (and its fingerprint, `settings()`)
    assert person_model_config(TrackSettings()).look_again
    off = person_model_config(
        TrackSettings(look_again=False, detect_every=5, still_change=0, look_again_zoom=0)
    )
    assert not off.look_again and off.detect_every == 5 and not off.settings()["look_again"]
    assert off.still_change == 0 and off.settings()["still_change"] == 0
    assert off.look_again_zoom == 0 and off.settings()["look_again_zoom"] == 0


@settings(max_examples=60, deadline=None)
@given(
    st.floats(1.0, 240.0),
    st.integers(1, 4),
    st.floats(0.01, 2.0),
    st.one_of(st.none(), st.integers(1, 50)),
)
def test_the_detector_looks_for_newcomers_every_few_tenths_of_a_second(fps, stride, every_s, n):
    """The person detector's interval in processed frames follows the video's rate and the
    stride (`detect_every_s`): 10 frames at 30 frames/s, 20 at 60, 10 at 60 with stride 2; a
    video whose rate is unknown counts as 30 frames/s; `detect_every` in frames overrides."""
    assert detector_interval(TrackSettings(), 30.0) == 10
    assert detector_interval(TrackSettings(), 60.0) == 20
    assert detector_interval(TrackSettings(stride=2), 60.0) == 10
    assert detector_interval(TrackSettings(), None) == detector_interval(TrackSettings(), 0.0) == 10
    s = TrackSettings(stride=stride, detect_every_s=every_s, detect_every=n)
    got = detector_interval(s, fps)
    assert person_model_config(s, fps=fps).detect_every == got
    if n is not None:
        assert got == n
    else:
        assert got >= 1
        # the run's period in seconds of video is the setting's, to half a processed frame
        assert got == 1 or abs(got * stride / fps - every_s) <= 0.5 * stride / fps + 1e-9


def test_a_jobs_torch_threads_are_put_back(monkeypatch):
    seen = []

    def fake_run(item):
        seen.append(torch.get_num_threads())
        raise RuntimeError("the job failed")

    monkeypatch.setattr(batch, "_run_item", fake_run)
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # the caller's pool, different from the job's
    try:
        job = batch.VideoJob(video=None, detector=None, predictor=None, model={}, threads=1)
        item = batch._Item(job, out_root=None, staging_root=None)
        with pytest.raises(RuntimeError, match="the job failed"):
            batch.run_item(item)
        assert seen == [1]
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_available_cores_follow_the_process_affinity(monkeypatch):
    import gst.cores as cores

    monkeypatch.setattr(cores.os, "cpu_count", lambda: 64)
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 3}, raising=False)
    assert cores.available_cores() == 2  # a container allowed 2 of the machine's 64

    def no_affinity(pid):
        raise AttributeError("no sched_getaffinity here")

    monkeypatch.setattr(cores.os, "sched_getaffinity", no_affinity, raising=False)
    assert cores.available_cores() == 64
    monkeypatch.setattr(cores.os, "cpu_count", lambda: None)
    assert cores.available_cores() == 1


def test_chunks_share_the_cores_as_videos_do():
    """With chunking the executor runs chunks, not videos: one chunked video on 2 workers gave
    each of its 2 chunks at once the threads of a video alone (6 threads on 2 cores)."""
    assert jobs_at_once(TrackSettings(), workers=2, videos=1) == 1
    assert jobs_at_once(TrackSettings(chunk_frames=100), workers=2, videos=1) == 2
    assert jobs_at_once(TrackSettings(chunk_frames=100), workers=1, videos=3) == 1
    assert jobs_at_once(TrackSettings(), workers=4, videos=3) == 3
