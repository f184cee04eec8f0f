"""The scene's `fps` (for videos whose headers are not trusted: a raw stream reads at FFmpeg's
25) reaches the stages that time frames: extract's keypoint tracker and track's rows. Only
fuse read it; a `--set scenes.NAME.fps=60` reran extract and track for nothing."""

from __future__ import annotations

import textwrap

import pytest

from pipeline.config import load_config
from pipeline.registry import load_stages
from pipeline.runner import Runner


def _context(tmp_path, stage: str, fps: float | None, options=None):
    cams = tmp_path / "cams"
    cams.mkdir(exist_ok=True)
    for n in ("cam01", "cam02"):
        (cams / f"{n}.mjpeg").write_bytes(b"")  # never opened: the library is replaced
    rate = "" if fps is None else f", fps: {fps}"
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        default_scene: lab
        scenes:
          lab: {{videos: cams/cam*.mjpeg{rate}}}
        stages:
          extract: {{module: "stages.extract:STAGE"}}
          track: {{module: "stages.track:STAGE"}}
        """)
    )
    config = load_config(cfg)
    runner = Runner(config, "lab", load_stages(config), options=options or {})
    ctx = runner.context(stage)
    ctx.params = runner._validate_params(stage)
    return ctx


@pytest.mark.parametrize("fps", [60.0, None])
def test_track_times_the_scene_videos_at_the_scene_rate(tmp_path, monkeypatch, fps):
    import stages.track

    seen = {}
    monkeypatch.setattr(stages.track, "track_scene", lambda s, req, **kw: seen.update(req=req))
    stages.track.run(_context(tmp_path, "track", fps))
    assert seen["req"].fps == fps
    # a video given on the command line is not the scene's: its own header stands
    stages.track.run(
        _context(tmp_path, "track", fps, {"video": [str(tmp_path / "cams/cam01.mjpeg")]})
    )
    assert seen["req"].fps is None


def test_a_raw_stream_given_with_video_takes_track_fps(tmp_path, monkeypatch):
    """A raw stream given with --video was timed at FFmpeg's 25 frames/s whatever its rate,
    and the warning's advice (the scene's fps) did not reach --video runs: `track.fps` does."""
    import stages.track

    seen = {}
    monkeypatch.setattr(stages.track, "track_scene", lambda s, req, **kw: seen.update(req=req))
    ctx = _context(tmp_path, "track", 30.0, {"video": [str(tmp_path / "cams/cam01.mjpeg")]})
    ctx.params = ctx.params.model_copy(update={"fps": 60.0})
    stages.track.run(ctx)
    assert seen["req"].fps == 60.0


def test_extract_times_its_keypoint_tracker_at_the_scene_rate(tmp_path, monkeypatch):
    import stages.extract

    seen = {}

    def fake_extract(videos, rig, out, **kw):
        seen.update(kw)
        raise RuntimeError("stop here")

    monkeypatch.setattr(stages.extract, "extract_scene", fake_extract)
    ctx = _context(tmp_path, "extract", 60.0)
    monkeypatch.setattr(type(ctx), "rig", lambda self: None)
    with pytest.raises(RuntimeError, match="stop here"):
        stages.extract.run(ctx)
    assert seen["options"].fps == 60.0
