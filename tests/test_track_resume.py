"""A run killed or failing mid-way resumes from its last committed row group and writes the
same bytes as an uninterrupted run; partial rows stay valid; bad partial state is refused."""

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from gst.track import (
    BoxDepthPredictor,
    OneEuroConfig,
    ResumeError,
    SuppliedBoxes,
    TrackOptions,
    VideoTruncatedError,
    read_tracks,
    track_video,
)
from gst.track.tracker import TrackerConfig
from gst.track.writer import default_staging_root
from tests.track_synthetic import MODEL, H, W, crossing_clip, write_boxes_csv

N = 40
# min_hits 3 and a third person who appears at frame 12: they are confirmed at frame 14, in the
# next group, so their rows of frames 12 and 13 are held in the committed state across the border.
OPTIONS = TrackOptions(
    frames_per_group=7,
    batch_size=5,
    smoothing=OneEuroConfig(0.8, 0.2, 1.0),
    tracker=TrackerConfig(min_hits=3),
)
LATE = 12
ROWS = 2 * N + (N - LATE)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    _, boxes, video = crossing_clip(d, N, W, H)
    visible = np.ones(boxes.shape[:2], bool)
    visible[:LATE, 2] = False
    return {"video": video, "csv": write_boxes_csv(d / "boxes.csv", boxes, "clip", visible)}


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    res = track(scene["video"], out, SuppliedBoxes.from_file(scene["csv"]))
    t = read_tracks(res.path)
    late = t.filter(pc.equal(t.column("person_id"), 2)).column("frame").to_pylist()
    assert late == list(range(LATE, N))  # rows from the first frame, though confirmed later
    return res.path.read_bytes()


def staging_of(out):
    return default_staging_root(out) / "video=clip"


def track(video: Path, out: Path, det: SuppliedBoxes, predictor=None, **kwargs):
    """track_video with the test model, OPTIONS unless given, BoxDepthPredictor by default."""
    kwargs.setdefault("options", OPTIONS)
    return track_video(video, out, det, predictor or BoxDepthPredictor(), model=MODEL, **kwargs)


class FailingPredictor(BoxDepthPredictor):
    def __init__(self, fail_on_call: int):
        super().__init__()
        self.calls, self.fail_on_call = 0, fail_on_call

    def __call__(self, crops, K_crop):
        self.calls += 1
        if self.calls == self.fail_on_call:
            raise RuntimeError("model crashed")
        return super().__call__(crops, K_crop)


def crash_mid_run(scene, out: Path, det: SuppliedBoxes, fail_on_call: int) -> None:
    """A run whose model crashes on call `fail_on_call`, leaving its committed rows staged."""
    with pytest.raises(RuntimeError, match="model crashed"):
        track(scene["video"], out, det, FailingPredictor(fail_on_call=fail_on_call))


def test_exception_mid_run_then_resume_is_identical(scene, reference, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    out = tmp_path / "out"
    crash_mid_run(scene, out, det, fail_on_call=13)
    assert not (out / "video=clip" / "tracks.parquet").exists()  # nothing presented as complete
    segments = sorted(staging_of(out).glob("seg-*.parquet"))
    assert 2 <= len(segments) < 6
    committed = pq.read_table(segments[-1])  # committed rows are valid Parquet
    assert committed.num_rows > 0
    progress = json.loads((staging_of(out) / "progress.json").read_text())
    before = progress["state"]["elapsed_s"]  # the killed part's time, kept beside the state
    assert before > 0
    res = track(scene["video"], out, det)
    assert res.resumed_from_frame == 7 * len(segments)
    assert res.path.read_bytes() == reference  # the time never enters the output
    assert res.seconds >= before  # frames/s of a resumed run count the earlier part's time too
    assert not default_staging_root(out).exists()


KILL_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, sys.argv[1])
    from gst.track import BoxDepthPredictor, OneEuroConfig, SuppliedBoxes, TrackOptions, track_video
    from gst.track.tracker import TrackerConfig

    class KillingPredictor(BoxDepthPredictor):
        calls = 0
        def __call__(self, crops, K_crop):
            KillingPredictor.calls += 1
            if KillingPredictor.calls == int(sys.argv[5]):
                os.kill(os.getpid(), signal.SIGKILL)
            return super().__call__(crops, K_crop)

    track_video(sys.argv[2], sys.argv[3], SuppliedBoxes.from_file(sys.argv[4]), KillingPredictor(),
                model={"name": "test-double", "version": "0"},
                options=TrackOptions(frames_per_group=7, batch_size=5,
                                     smoothing=OneEuroConfig(0.8, 0.2, 1.0),
                                     tracker=TrackerConfig(min_hits=3)))
""")


@pytest.mark.parametrize("kill_on_call", [8, 17])  # 8: while the late person's rows are held
def test_kill_9_then_rerun_gives_the_identical_file(scene, reference, tmp_path, kill_on_call):
    script = tmp_path / "run.py"
    script.write_text(KILL_SCRIPT)
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            str(script),
            str(REPO),
            str(scene["video"]),
            str(out),
            str(scene["csv"]),
            str(kill_on_call),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    staging = staging_of(out)
    assert (staging / "progress.json").exists() and not (
        out / "video=clip" / "tracks.parquet"
    ).exists()
    res = track(scene["video"], out, SuppliedBoxes.from_file(scene["csv"]))
    # call 8 is the first batch of frames 14..20: the late person's rows of 12, 13 were held
    assert res.resumed_from_frame == (14 if kill_on_call == 8 else 21)
    assert res.path.read_bytes() == reference
    t = read_tracks(res.path)
    keys = list(zip(t.column("frame").to_pylist(), t.column("person_id").to_pylist(), strict=True))
    assert len(keys) == len(set(keys)) == ROWS  # no duplicates, nothing missing


def test_orphan_segment_from_an_interrupted_commit_is_discarded(scene, reference, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    crash_mid_run(scene, tmp_path / "out", det, fail_on_call=10)
    staging = staging_of(tmp_path / "out")
    segs = sorted(staging.glob("seg-*.parquet"))
    # a kill between writing a segment and recording it leaves an unrecorded segment behind
    (staging / f"seg-{len(segs):06d}.parquet").write_bytes(segs[0].read_bytes())
    res = track(scene["video"], tmp_path / "out", det)
    assert res.path.read_bytes() == reference


def test_resume_with_other_settings_is_refused_with_the_reason(scene, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    crash_mid_run(scene, tmp_path / "out", det, fail_on_call=10)
    plain = TrackOptions(frames_per_group=7, batch_size=5)
    with pytest.raises(
        ResumeError,
        match=r"different settings exists \(changed: \['options.smoothing', "
        r"'options.tracker.min_hits'\]\)",
    ):
        track(scene["video"], tmp_path / "out", det, options=plain)
    res = track(scene["video"], tmp_path / "out", det, options=plain, resume=False)
    assert res.resumed_from_frame is None and res.rows == ROWS


def test_finished_output_is_not_recomputed(scene, reference, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    track(scene["video"], tmp_path / "out", det)
    staging_of(tmp_path / "out").mkdir(parents=True)  # as if killed after the final rename
    never = FailingPredictor(fail_on_call=1)
    res = track(scene["video"], tmp_path / "out", det, never)
    assert never.calls == 0 and res.rows == ROWS and res.path.read_bytes() == reference
    assert not default_staging_root(tmp_path / "out").exists()


def test_truncated_video_errors_and_keeps_the_rows_before_it(scene, tmp_path):
    cut = tmp_path / "clip.avi"
    data = scene["video"].read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    det = SuppliedBoxes.from_file(scene["csv"])
    with pytest.raises(
        VideoTruncatedError, match=r"clip.avi: decoding failed at frame (\d+)"
    ) as err:
        track(cut, tmp_path / "out", det)
    bad = err.value.frame
    staging = staging_of(tmp_path / "out")
    rows = pq.ParquetDataset(sorted(staging.glob("seg-*.parquet")), partitioning=None).read()
    assert sorted(set(rows.column("frame").to_pylist())) == list(range(bad))
    assert not (tmp_path / "out" / "video=clip" / "tracks.parquet").exists()
    # a rerun on the same damaged file resumes at the damage and stops there again
    with pytest.raises(VideoTruncatedError):
        track(cut, tmp_path / "out", det)
    np.testing.assert_array_equal(
        pq.ParquetDataset(sorted(staging.glob("seg-*.parquet")), partitioning=None)
        .read()
        .column("frame")
        .to_numpy(),
        rows.column("frame").to_numpy(),
    )


def test_unreadable_progress_record_is_reported(scene, tmp_path):
    det = SuppliedBoxes.from_file(scene["csv"])
    crash_mid_run(scene, tmp_path / "out", det, fail_on_call=10)
    progress = staging_of(tmp_path / "out") / "progress.json"
    progress.write_text("{not json")
    with pytest.raises(ResumeError, match="progress.json: unreadable progress record"):
        track(scene["video"], tmp_path / "out", det)
    os.remove(progress)


def test_a_supplied_box_files_content_is_part_of_the_runs_settings(tmp_path):
    """The detector's description named the box file's path alone: boxes edited between an
    interrupted run and its resume were mixed into one tracks file (and a finished file of the
    old boxes kept)."""
    from gst.track.scene import _detector_info

    boxes = tmp_path / "boxes.csv"
    boxes.write_text("video,frame,x0,y0,x1,y1\nclip,0,10,20,60,100\n")
    before = _detector_info("boxes", f"boxes supplied in {boxes}", None, boxes)
    boxes.write_text("video,frame,x0,y0,x1,y1\nclip,0,20,20,70,100\n")  # the same size
    after = _detector_info("boxes", f"boxes supplied in {boxes}", None, boxes)
    assert before != after and before["why"] == after["why"]
    # a long file fixed in its middle keeps its size and ends (a sampled digest's view of it)
    import gst.video

    head = "video,frame,x0,y0,x1,y1\n"
    rows = [f"clip,{i},10,20,60,100\n" for i in range(3000)]
    boxes.write_text(head + "".join(rows))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(gst.video, "CONTENT_SAMPLE_BYTES", 4096)
        before = _detector_info("boxes", "supplied", None, boxes)
        rows[1500] = "clip,1500,30,20,80,100\n"  # moved 20 px, the same length
        boxes.write_text(head + "".join(rows))
        assert _detector_info("boxes", "supplied", None, boxes) != before


def test_a_copy_across_file_systems_never_leaves_a_file_inside_the_dataset(tmp_path, monkeypatch):
    """With the staging root on another file system, finalize copied into a hidden file inside
    video=<name>/; a kill during the copy left it there, and readers that read hidden files
    (polars, duckdb) took its rows as tracks. The copy now lands beside the dataset."""
    import errno
    import os
    import shutil

    import pyarrow as pa

    import gst.track.writer as writer_module
    from gst.track.writer import TrackWriter

    schema = pa.schema([("frame", pa.int64()), ("person_id", pa.int64())])
    root = tmp_path / "tracks"
    real_replace, real_copy = os.replace, shutil.copyfile

    def replace_across(src, dst):
        if ".inprogress" in str(src) and ".inprogress" not in str(dst):  # staged -> final
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return real_replace(src, dst)

    at_kill: list[str] = []

    def killed_copy(src, dst):
        real_copy(src, dst)
        # what a kill at this moment leaves in the dataset (Python's clean-up would not run)
        at_kill.extend(p.name for p in (root / "video=cam").glob("*"))
        raise KeyboardInterrupt

    def new_writer():
        w = TrackWriter(root, "cam", schema, {"a": 1}, staging_root=tmp_path / ".inprogress")
        w.start(resume=False)
        w.commit(pa.table({"frame": [0, 1], "person_id": [0, 0]}, schema=schema), 2, {})
        return w

    monkeypatch.setattr(writer_module.os, "replace", replace_across)
    monkeypatch.setattr(writer_module.shutil, "copyfile", killed_copy)
    with pytest.raises(KeyboardInterrupt):
        new_writer().finalize({})
    assert at_kill == []  # nothing a dataset reader would take for rows
    monkeypatch.setattr(writer_module.shutil, "copyfile", real_copy)
    path = new_writer().finalize({})
    assert [p.name for p in path.parent.iterdir()] == ["tracks.parquet"]
    assert pq.read_table(path).num_rows == 2
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir() if p.is_file())
