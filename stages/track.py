"""track: per-frame GST inference on videos, written as pose time series to Parquet.

`python -m pipeline run track --video match.mp4` tracks that video; without `--video` it tracks
the scene's own camera videos. A video whose file name matches a calibrated camera of the scene
uses that camera (world coordinates are written); any other video uses the default camera
(docs/formats/tracks_parquet.md). Output: `tracks/video=<name>/tracks.parquet` (Hive-partitioned,
one row per frame and person), `reports/track/<name>/` (overlay video, joint-angle plot) and,
with `--with-gaussians`, `models/splats/<name>/person_<id>.ply`.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from calibration.formats import read_rig
from gst.model.inference import GSTPredictor
from gst.render.ply import write_gaussians_ply
from gst.track import OneEuroConfig, TrackOptions, track_video
from gst.track.detection import SuppliedBoxes
from gst.track.report import plot_joint_angles, write_overlay
from gst.track.static_detector import StaticCameraDetector
from gst.track.tracker import TrackerConfig
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    stride: int = 1
    start_s: float | None = None
    end_s: float | None = None
    batch_size: int = 32
    smoothing: bool = False  # One-Euro filter on joints and parameters
    min_cutoff: float = 1.0
    beta: float = 0.5
    boxes: Path | None = None  # supplied boxes (CSV/Parquet) instead of the background detector
    overlay: bool = True  # write an overlay video per track (skeletons, boxes, ids)
    threads: int | None = None
    min_hits: int = 3  # consecutive detections before a new person gets an id
    max_misses: int = 30  # processed frames a person may go undetected and keep the id


def _videos(ctx: StageContext) -> list[Path]:
    given = [Path(v) for v in ctx.options.get("video") or []]
    if given:
        missing = [str(v) for v in given if not v.is_file()]
        if missing:
            raise FileNotFoundError(f"--video: no such file(s): {missing}")
        return given
    if ctx.scene.is_synthetic:
        return sorted(ctx.path("synth/videos").glob("*.mp4"))
    return ctx.scene.video_files()


def _variant(ctx: StageContext) -> str | None:
    given = ctx.options.get("video") or []
    return "+".join(sorted(Path(v).stem for v in given)) or None


def run(ctx: StageContext) -> None:
    p = ctx.params
    if p.threads:
        torch.set_num_threads(p.threads)
    with_gaussians = bool(ctx.options.get("with_gaussians"))
    predictor = GSTPredictor(ctx.path("models/gst.pt"), with_gaussians=with_gaussians, batch_size=p.batch_size)
    rig_path = ctx.path("calibration/rig.json")
    rig = read_rig(rig_path, "rig") if rig_path.is_file() else None
    options = TrackOptions(stride=p.stride, tracker=TrackerConfig(min_hits=p.min_hits, max_misses=p.max_misses), start_s=p.start_s, end_s=p.end_s, batch_size=p.batch_size,
                           smoothing=OneEuroConfig(min_cutoff=p.min_cutoff, beta=p.beta) if p.smoothing else None)
    model_info = {"name": predictor.name, "version": "1", "checkpoint": "models/gst.pt"}
    for video in ctx.track(_videos(ctx), "videos"):
        name = video.stem
        camera = rig[name] if rig is not None and name in rig.names else None
        detector = (SuppliedBoxes.from_file(p.boxes, video=name) if p.boxes else
                    StaticCameraDetector(video, camera=camera, up=rig.up if camera is not None else (0.0, 0.0, 1.0)))
        splats: dict[int, dict] = {}

        def keep_splat(frame: int, person: int, extra: dict, splats=splats) -> None:
            if person not in splats and "gaussian_means" in extra:
                splats[person] = extra

        result = track_video(video, ctx.out("tracks"), detector, predictor, model=model_info, camera=camera,
                             video_name=name, options=options, staging_root=ctx.staging / "inprogress",
                             world_up=rig.up if (rig is not None and camera is not None) else None,
                             on_extra=keep_splat if with_gaussians else None)
        summary = {"rows": result.rows, "frames": result.frames, "persons": result.persons,
                   "seconds": round(result.seconds, 2), "fps": round(result.frames / max(result.seconds, 1e-9), 2),
                   "calibrated": camera is not None}
        ctx.log.info("%s: %d frames, %d people, %.1f frames/s", name, result.frames, result.persons,
                     result.frames / max(result.seconds, 1e-9))
        report = ctx.out(f"reports/track/{name}/x").parent
        report.mkdir(parents=True, exist_ok=True)
        (report / "summary.json").write_text(json.dumps(summary, indent=2))
        if p.overlay:
            write_overlay(video, result.path, report / "overlay.mp4")
        plot_joint_angles(result.path, report / "joint_angles.png")
        for person, g in splats.items():
            write_gaussians_ply(ctx.out(f"models/splats/{name}/person_{person}.ply"), g["gaussian_means"],
                                g["gaussian_quats"], g["gaussian_scales"], g["gaussian_opacities"], g["gaussian_colors"])


def _outputs(ctx: StageContext) -> list[str]:
    names = [v.stem for v in _videos(ctx)]
    outs = [f"tracks/video={n}" for n in names] + [f"reports/track/{n}" for n in names]
    if ctx.options.get("with_gaussians"):
        outs += [f"models/splats/{n}" for n in names]
    return outs


STAGE = Stage(name="track", run=run, params_model=Params, resumable=True, variant=_variant,
              inputs=lambda ctx: _videos(ctx) if ctx.options.get("video") or not ctx.scene.is_synthetic else [],
              outputs=_outputs, cli_options=("video", "with_gaussians"),
              help="per-frame inference on videos -> tracks/video=<name>/tracks.parquet")
