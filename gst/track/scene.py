"""Track a scene's videos (or any video): pick the person detector, run the tracking jobs
through an executor, and write each video's report.

`track_scene(settings, request)` builds one `VideoJob` per video (its calibrated camera when the
file name is one of the rig's cameras, the default camera otherwise), tracks them
(`gst.track.batch.track_videos`, optionally in chunks), then writes per video a summary, an
overlay video, a joint-angle plot, splats on request and, for a synthetic scene's own cameras,
an evaluation against the truth (`gst.track.evaluate`).
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field

from calibration import Camera, Rig
from calibration.camera import FRAME_PADDING_TOLERANCE, fit_to_frames
from gst.detect.weights import model_paths
from gst.model.inference import GSTPredictor
from gst.render.ply import write_gaussians_ply
from gst.track.batch import VideoJob, VideoOutcome, track_videos
from gst.track.chunks import ChunkingConfig
from gst.track.detection import SuppliedBoxes
from gst.track.evaluate import TrackEvaluation, evaluate_tracks
from gst.track.evaluation_report import write_evaluation_json, write_evaluation_markdown
from gst.track.loop import TrackOptions
from gst.track.person_detector import PersonModelDetector
from gst.track.report import plot_joint_angles, write_overlay
from gst.track.smoothing import OneEuroConfig
from gst.track.static_detector import StaticCameraDetector
from gst.track.tracker import TrackerConfig
from gst.video import probe_video
from synth.truth import has_scene_truth

log = logging.getLogger("gst.track")


class TrackSettings(BaseModel):
    """Settings of tracking (the `track` stage's parameters)."""

    model_config = ConfigDict(extra="forbid")

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


@dataclass(frozen=True)
class TrackRequest:
    """What to track and where to write it. `truth_scene`: a synthetic scene folder whose
    cameras' videos are scored against its truth; `combined_evaluation`: where to write the
    evaluation of all of them together (None: no combined file)."""

    videos: list[Path]
    checkpoint: Path
    rig: Rig | None
    tracks_dir: Path
    reports_dir: Path
    staging: Path
    splats_dir: Path | None = None  # per-person splat PLYs (`--with-gaussians`)
    truth_scene: Path | None = None
    combined_evaluation: Path | None = None
    frame_size_tolerance: int = FRAME_PADDING_TOLERANCE  # calibration.camera.fit_to_frames


def _detector(s: TrackSettings, video: Path, camera: Camera | None, rig: Rig | None) -> Callable:
    """A picklable factory of the video's person detector: supplied boxes, the learned person
    model, or the static-camera background model."""
    if s.boxes:
        return functools.partial(SuppliedBoxes.from_file, s.boxes, video=video.stem)
    if s.detector == "blazepose":
        return PersonModelDetector
    up = tuple(rig.up) if camera is not None else (0.0, 0.0, 1.0)
    return functools.partial(StaticCameraDetector, video, camera=camera, up=up)


def track_scene(
    s: TrackSettings,
    request: TrackRequest,
    *,
    map_fn: Callable | None = None,
    workers: int = 1,
) -> list[VideoOutcome]:
    """Track every video of the request and write its reports (see the module doc)."""
    if s.threads:
        torch.set_num_threads(s.threads)
    with_gaussians = request.splats_dir is not None
    # Load the model once here: a bad checkpoint fails now, naming the file, not in a worker.
    name = GSTPredictor(
        request.checkpoint, with_gaussians=with_gaussians, batch_size=s.batch_size
    ).name
    if s.detector == "blazepose" and not s.boxes:
        model_paths()  # missing models fail here, with the fetch command, not in a worker
    options = TrackOptions(
        stride=s.stride,
        tracker=TrackerConfig(min_hits=s.min_hits, max_misses=s.max_misses),
        start_s=s.start_s,
        end_s=s.end_s,
        batch_size=s.batch_size,
        smoothing=OneEuroConfig(min_cutoff=s.min_cutoff, beta=s.beta) if s.smoothing else None,
    )
    model_info = {"name": name, "version": "1", "checkpoint": "models/gst.pt"}
    # Parallel workers share the cores: one torch thread each unless told otherwise.
    threads = s.threads or (1 if workers > 1 else None)
    predictor = functools.partial(
        GSTPredictor, request.checkpoint, with_gaussians=with_gaussians, batch_size=s.batch_size
    )
    rig = request.rig
    jobs = []
    for video in request.videos:
        camera = rig[video.stem] if rig is not None and video.stem in rig.names else None
        if camera is not None:  # fitted to the frames now: a size mismatch fails here, named
            info = probe_video(video, camera.name)
            camera, note = fit_to_frames(
                camera, info.width, info.height, request.frame_size_tolerance, str(video)
            )
            if note:
                log.warning("%s", note)
        jobs.append(
            VideoJob(
                video,
                _detector(s, video, camera, rig),
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
    chunking = ChunkingConfig(s.chunk_frames, s.chunk_overlap) if s.chunk_frames else None
    outcomes = track_videos(
        jobs,
        request.tracks_dir,
        map_fn=map_fn,
        staging_root=request.staging,
        chunking=chunking,
        description="track videos" + (" (chunks)" if chunking else ""),
    )
    evaluations = [write_video_report(s, request, o) for o in outcomes]
    if request.combined_evaluation is not None:
        scored = [e for e in evaluations if e is not None]
        write_evaluation_markdown(scored, request.combined_evaluation)
    return outcomes


def _truth_camera(request: TrackRequest, video: Path) -> str | None:
    """The synthetic scene camera a video shows (its file name is a camera's video), else None."""
    scene = request.truth_scene
    if scene is None or not has_scene_truth(scene):
        return None
    return video.stem if (scene / "videos" / f"{video.stem}.mp4").is_file() else None


def _mm(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} mm"


def _evaluate(request: TrackRequest, outcome: VideoOutcome, report: Path) -> TrackEvaluation | None:
    """Score a synthetic camera's tracks against the truth: evaluation.json, and a log line."""
    camera = _truth_camera(request, outcome.job.video)
    if camera is None:
        return None
    ev = evaluate_tracks(outcome.result.path, request.truth_scene, camera)
    write_evaluation_json(ev, report / "evaluation.json")
    log.info(
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


def write_video_report(
    s: TrackSettings, request: TrackRequest, outcome: VideoOutcome
) -> TrackEvaluation | None:
    """Summary, overlay video, joint-angle plot and splats of one tracked video; its evaluation
    against the truth when it is a synthetic scene's camera."""
    name, result = outcome.job.name, outcome.result
    fps = result.frames / max(result.seconds, 1e-9)
    summary = {
        "rows": result.rows,
        "frames": result.frames,
        "persons": result.persons,
        "seconds": round(result.seconds, 2),
        "fps": round(fps, 2),
        "calibrated": outcome.job.camera is not None,
        "chunks": outcome.chunks,
    }
    log.info("%s: %d frames, %d people, %.1f frames/s", name, result.frames, result.persons, fps)
    report = request.reports_dir / name
    report.mkdir(parents=True, exist_ok=True)
    (report / "summary.json").write_text(json.dumps(summary, indent=2))
    if s.overlay:
        write_overlay(outcome.job.video, result.path, report / "overlay.mp4")
    plot_joint_angles(result.path, report / "joint_angles.png")
    evaluation = _evaluate(request, outcome, report)
    for person, g in outcome.extras.items():
        if "gaussian_means" in g and request.splats_dir is not None:
            write_gaussians_ply(
                request.splats_dir / name / f"person_{person}.ply",
                g["gaussian_means"],
                g["gaussian_quats"],
                g["gaussian_scales"],
                g["gaussian_opacities"],
                g["gaussian_colors"],
            )
    return evaluation
