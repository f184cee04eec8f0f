"""track: per-frame GST inference on videos, written as pose time series to Parquet.

`python -m pipeline run track --video match.mp4` tracks that video; without `--video` it tracks
the scene's own camera videos. A video whose file name matches a calibrated camera of the scene
uses that camera (world coordinates are written); any other video uses the default camera
(docs/formats/tracks_parquet.md). Output: `tracks/video=<name>/tracks.parquet` (Hive-partitioned,
one row per frame and person), `reports/track/<name>/` (overlay video, joint-angle plot) and,
with `--with-gaussians`, `models/splats/<name>/person_<id>.ply`.

On a synthetic scene, a video of one of the scene's cameras is scored against the scene's truth
(gst/track/evaluate.py, docs/track_evaluation.md): `reports/track/<name>/evaluation.json`, and
for a run over the scene's own videos a combined `reports/track/evaluation.md`.

Videos are fanned out through the executor (`--executor local|ray`, `--workers`), one item per
video; with `--set track.chunk_frames=N` a video longer than N processed frames is split into
chunks tracked in parallel and stitched (gst/track/chunks.py). Reports are written here, after.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Literal

import torch
from pydantic import Field

from calibration.formats import read_rig
from gst.detect.weights import model_paths
from gst.eval.truth import has_scene_truth
from gst.model.inference import GSTPredictor
from gst.render.ply import write_gaussians_ply
from gst.track import OneEuroConfig, TrackOptions
from gst.track.batch import VideoJob, VideoOutcome, track_videos
from gst.track.chunks import ChunkingConfig
from gst.track.detection import SuppliedBoxes
from gst.track.evaluate import TrackEvaluation, evaluate_tracks
from gst.track.evaluation_report import write_evaluation_json, write_evaluation_markdown
from gst.track.person_detector import PersonModelDetector
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
    # 'blazepose': the learned person segmenter (gst.detect; finds people who stand still, needs
    # the `detect` extra and `python -m gst.detect fetch`). 'background': static-camera model.
    detector: Literal["background", "blazepose"] = "background"
    overlay: bool = True  # write an overlay video per track (skeletons, boxes, ids)
    threads: int | None = None
    min_hits: int = 3  # consecutive detections before a new person gets an id
    max_misses: int = 30  # processed frames a person may go undetected and keep the id
    # Split videos longer than this many processed frames into chunks tracked in parallel and
    # stitched (gst/track/chunks.py); off by default because ids can differ where tracking is
    # ambiguous at a border. Not with smoothing or --with-gaussians.
    chunk_frames: int | None = Field(default=None, ge=1)
    chunk_overlap: int = Field(default=30, ge=1)


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


def _map(ctx: StageContext):
    return ctx.executor.map if ctx.executor is not None else None


def run(ctx: StageContext) -> None:
    p = ctx.params
    if p.threads:
        torch.set_num_threads(p.threads)
    with_gaussians = bool(ctx.options.get("with_gaussians"))
    checkpoint = ctx.path("models/gst.pt")
    name = GSTPredictor(
        checkpoint, with_gaussians=with_gaussians, batch_size=p.batch_size
    ).name  # fails early, here
    if p.detector == "blazepose" and not p.boxes:
        model_paths()  # missing models fail here, with the fetch command, not in a worker
    rig_path = ctx.path("calibration/rig.json")
    rig = read_rig(rig_path, "rig") if rig_path.is_file() else None
    options = TrackOptions(
        stride=p.stride,
        tracker=TrackerConfig(min_hits=p.min_hits, max_misses=p.max_misses),
        start_s=p.start_s,
        end_s=p.end_s,
        batch_size=p.batch_size,
        smoothing=OneEuroConfig(min_cutoff=p.min_cutoff, beta=p.beta) if p.smoothing else None,
    )
    model_info = {"name": name, "version": "1", "checkpoint": "models/gst.pt"}
    workers = getattr(ctx.executor, "workers", 1)
    # Parallel workers share the cores: one torch thread each unless told otherwise.
    threads = p.threads or (1 if workers > 1 else None)
    predictor = functools.partial(
        GSTPredictor, checkpoint, with_gaussians=with_gaussians, batch_size=p.batch_size
    )
    jobs = []
    for video in _videos(ctx):
        camera = rig[video.stem] if rig is not None and video.stem in rig.names else None
        if p.boxes:
            detector = functools.partial(SuppliedBoxes.from_file, p.boxes, video=video.stem)
        elif p.detector == "blazepose":
            detector = PersonModelDetector
        else:
            detector = functools.partial(
                StaticCameraDetector,
                video,
                camera=camera,
                up=tuple(rig.up) if camera is not None else (0.0, 0.0, 1.0),
            )
        jobs.append(
            VideoJob(
                video,
                detector,
                predictor,
                model_info,
                name=video.stem,
                camera=camera,
                world_up=tuple(rig.up) if (rig is not None and camera is not None) else None,
                options=options,
                threads=threads,
                keep_extras=with_gaussians,
            )
        )
    chunking = ChunkingConfig(p.chunk_frames, p.chunk_overlap) if p.chunk_frames else None
    outcomes = track_videos(
        jobs,
        ctx.out("tracks"),
        map_fn=_map(ctx),
        staging_root=ctx.staging / "inprogress",
        chunking=chunking,
        description="track videos" + (" (chunks)" if chunking else ""),
    )
    evaluations = [e for e in (_report(ctx, outcome) for outcome in outcomes) if e is not None]
    if _writes_combined_evaluation(ctx):
        write_evaluation_markdown(evaluations, ctx.out("reports/track/evaluation.md"))


def _truth_camera(ctx: StageContext, video: Path) -> str | None:
    """The synthetic scene camera a video shows (its file name is a camera's video), else None."""
    if not ctx.scene.is_synthetic or not has_scene_truth(ctx.path("synth")):
        return None
    return video.stem if (ctx.path("synth/videos") / f"{video.stem}.mp4").is_file() else None


def _writes_combined_evaluation(ctx: StageContext) -> bool:
    """A run over a synthetic scene's own videos (not --video) writes reports/track/evaluation.md."""
    return ctx.scene.is_synthetic and not ctx.options.get("video")


def _mm(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} mm"


def _evaluate(ctx: StageContext, outcome: VideoOutcome, report: Path) -> TrackEvaluation | None:
    """Score a synthetic camera's tracks against the truth: evaluation.json, and a log line."""
    camera = _truth_camera(ctx, outcome.job.video)
    if camera is None:
        return None
    ev = evaluate_tracks(outcome.result.path, ctx.path("synth"), camera)
    write_evaluation_json(ev, report / "evaluation.json")
    ctx.log.info(
        "%s vs truth: MPJPE %s (PA %s, root %s), %d id switches, %d fragments, recall %.3f, "
        "precision %.3f",
        ev.video,
        _mm(ev.mpjpe_mm),
        _mm(ev.pa_mpjpe_mm),
        _mm(ev.root_error_mm),
        ev.id_switches,
        ev.fragments,
        ev.recall,
        ev.precision,
    )
    return ev


def _report(ctx: StageContext, outcome: VideoOutcome) -> TrackEvaluation | None:
    """Summary, overlay video, joint-angle plot and splats of one tracked video (in the caller)."""
    name, result = outcome.job.name, outcome.result
    summary = {
        "rows": result.rows,
        "frames": result.frames,
        "persons": result.persons,
        "seconds": round(result.seconds, 2),
        "fps": round(result.frames / max(result.seconds, 1e-9), 2),
        "calibrated": outcome.job.camera is not None,
        "chunks": outcome.chunks,
    }
    ctx.log.info(
        "%s: %d frames, %d people, %.1f frames/s",
        name,
        result.frames,
        result.persons,
        result.frames / max(result.seconds, 1e-9),
    )
    report = ctx.out(f"reports/track/{name}/x").parent
    report.mkdir(parents=True, exist_ok=True)
    (report / "summary.json").write_text(json.dumps(summary, indent=2))
    if ctx.params.overlay:
        write_overlay(outcome.job.video, result.path, report / "overlay.mp4")
    plot_joint_angles(result.path, report / "joint_angles.png")
    evaluation = _evaluate(ctx, outcome, report)
    for person, g in outcome.extras.items():
        if "gaussian_means" in g:
            write_gaussians_ply(
                ctx.out(f"models/splats/{name}/person_{person}.ply"),
                g["gaussian_means"],
                g["gaussian_quats"],
                g["gaussian_scales"],
                g["gaussian_opacities"],
                g["gaussian_colors"],
            )
    return evaluation


def _outputs(ctx: StageContext) -> list[str]:
    names = [v.stem for v in _videos(ctx)]
    outs = [f"tracks/video={n}" for n in names] + [f"reports/track/{n}" for n in names]
    if ctx.options.get("with_gaussians"):
        outs += [f"models/splats/{n}" for n in names]
    if _writes_combined_evaluation(ctx):
        outs.append("reports/track/evaluation.md")
    return outs


STAGE = Stage(
    name="track",
    run=run,
    params_model=Params,
    resumable=True,
    variant=_variant,
    inputs=lambda ctx: (
        _videos(ctx) if ctx.options.get("video") or not ctx.scene.is_synthetic else []
    ),
    outputs=_outputs,
    cli_options=("video", "with_gaussians"),
    help="per-frame inference on videos -> tracks/video=<name>/tracks.parquet",
)
