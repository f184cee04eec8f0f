"""track: per-frame GST inference on videos, written as pose time series to Parquet.

`python -m pipeline run track --video match.mp4` tracks that video; without `--video` it tracks
the scene's own camera videos. Library: `gst.track.scene.track_scene`. A video whose file name
matches a calibrated camera of the scene uses that camera (world coordinates are written); any
other video uses the default camera (docs/formats/tracks_parquet.md). Output:
`tracks/video=<name>/tracks.parquet`, `reports/track/<name>/` (overlay video, joint-angle plot;
on synthetic scenes an evaluation against the truth, docs/track_evaluation.md) and, with
`--with-gaussians`, `models/splats/<name>/person_<id>.ply`. Videos fan out through the executor.
"""

from __future__ import annotations

from pathlib import Path

from gst.track.scene import TrackRequest, TrackSettings, track_scene
from gst.track.writer import partition_dir
from pipeline.stage import Stage, StageContext


def _videos(ctx: StageContext) -> list[Path]:
    given = [Path(v) for v in ctx.options.get("video") or []]
    if given:
        missing = [str(v) for v in given if not v.is_file()]
        if missing:
            raise FileNotFoundError(f"--video: no such file(s): {missing}")
        return given
    return list(ctx.camera_videos().values())


def _variant(ctx: StageContext) -> str | None:
    return "+".join(sorted(Path(v).stem for v in ctx.options.get("video") or [])) or None


def _own_videos(ctx: StageContext) -> bool:
    """A run over a synthetic scene's own videos (not --video) writes a combined evaluation."""
    return ctx.scene.is_synthetic and not ctx.options.get("video")


def run(ctx: StageContext) -> None:
    rig_path = ctx.path("calibration/rig.json")
    request = TrackRequest(
        videos=_videos(ctx),
        checkpoint=ctx.path("models/gst.pt"),
        rig=ctx.rig() if rig_path.is_file() else None,
        tracks_dir=ctx.out("tracks"),
        reports_dir=ctx.out("reports/track"),
        staging=ctx.staging / "inprogress",
        splats_dir=ctx.out("models/splats") if ctx.options.get("with_gaussians") else None,
        truth_scene=ctx.path("synth") if ctx.scene.is_synthetic else None,
        combined_evaluation=ctx.out("reports/track/evaluation.md") if _own_videos(ctx) else None,
        frame_size_tolerance=ctx.scene.frame_size_tolerance,
        scene=ctx.scene_name,
        detections_cache=ctx.path(".pipeline/cache/detections"),
        fps=ctx.params.fps if ctx.options.get("video") else ctx.scene.fps,  # None: container's
    )
    executor = ctx.executor
    track_scene(ctx.params, request, map_fn=executor.map if executor is not None else None,
                workers=getattr(executor, "workers", 1))  # fmt: skip


def _outputs(ctx: StageContext) -> list[str]:
    names = [v.stem for v in _videos(ctx)]
    outs = [partition_dir("tracks", n).as_posix() for n in names]
    outs += [f"reports/track/{n}" for n in names]
    if ctx.options.get("with_gaussians"):
        outs += [f"models/splats/{n}" for n in names]
    return outs + (["reports/track/evaluation.md"] if _own_videos(ctx) else [])


STAGE = Stage(
    name="track", run=run, params_model=TrackSettings, resumable=True, variant=_variant,
    inputs=lambda ctx: [] if _own_videos(ctx) else _videos(ctx),
    outputs=_outputs, cli_options=("video", "with_gaussians"),
    help="per-frame inference on videos -> tracks/video=<name>/tracks.parquet",
)  # fmt: skip
