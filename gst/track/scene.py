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
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import torch
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    model_validator,
)

from calibration import Camera, Rig
from calibration.camera import FRAME_PADDING_TOLERANCE, CameraError, fit_to_frames
from gst.atomic import atomic_write, atomic_write_text
from gst.body import BodyModel, load_body_model
from gst.body.markers import MarkerModel
from gst.cores import available_cores
from gst.data.camera_view import TrackingView
from gst.detect.blazepose import import_litert
from gst.detect.weights import BlazePoseModelsMissing, model_paths
from gst.device import check_device_name, resolve_device
from gst.model.checkpoint import load_checkpoint
from gst.model.inference import GSTPredictor
from gst.registry import sha256_of
from gst.render.ply import write_gaussians_ply
from gst.track.agreement import (
    LandmarkAgreement,
    body_markers_2d,
    joints_vs_landmarks,
    markers_vs_landmarks,
)
from gst.track.align import AlignmentConfig
from gst.track.batch import VideoJob, VideoOutcome, check_unique_names, track_videos
from gst.track.chunks import ChunkingConfig
from gst.track.detection import SuppliedBoxes
from gst.track.evaluate import TrackEvaluation, evaluate_tracks
from gst.track.evaluation_report import write_evaluation_json, write_evaluation_markdown
from gst.track.loop import TrackOptions
from gst.track.mirror import MirrorConfig
from gst.track.person_detector import PersonModelConfig, PersonModelDetector
from gst.track.pose_fit import PoseFitConfig
from gst.track.read import read_tracks
from gst.track.report import contact_sheet, plot_joint_angles, write_overlay
from gst.track.schema import parse_metadata
from gst.track.smoothing import OneEuroConfig
from gst.track.static_detector import StaticCameraDetector
from gst.track.tracker import TrackerConfig
from gst.video import VideoError, file_identity, probe_video, still_image_error
from synth.truth import has_scene_truth

log = logging.getLogger("gst.track")


class TrackSettings(BaseModel):
    """Settings of tracking (the `track` stage's parameters)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    stride: PositiveInt = 1  # track every Nth frame
    start_s: float | None = Field(None, ge=0)  # from this time in the video (s; None: its start)
    end_s: float | None = Field(None, gt=0)  # up to this time (s; None: its end)
    # frame rate of `--video` files (frames/s; None: their container's): a raw stream (.h264,
    # .mjpeg) holds none and is read at FFmpeg's guess of 25. A scene's own cameras take the
    # scene's `fps`
    fps: PositiveFloat | None = None
    batch_size: PositiveInt = 32  # crops per network call
    smoothing: bool = False  # One-Euro filter on joints and parameters
    min_cutoff: PositiveFloat = 1.0  # One-Euro: cutoff (Hz) at rest; lower is smoother
    beta: NonNegativeFloat = 0.5  # One-Euro: how fast the cutoff rises with speed
    boxes: Path | None = None  # supplied boxes (CSV/Parquet) instead of a detector
    # 'auto': the learned person model (BlazePose, gst.detect) when it is installed (the `detect`
    # extra and `python -m gst.detect fetch`), else the static-camera background model.
    # 'blazepose' requires it; 'background' always uses the background model.
    detector: Literal["auto", "background", "blazepose"] = "auto"
    # blazepose: while everyone is tracked, the detector looks for new arrivals every this many
    # seconds of video (in processed frames: the video's rate / stride x this, rounded, at least
    # 1; 10 at 30 frames/s, 20 at 60), so that a newcomer waits as long at any frame rate
    detect_every_s: float = Field(default=1 / 3, gt=0)
    detect_every: int | None = Field(default=None, ge=1)  # processed frames instead of seconds
    # blazepose: each detector run looks once more with the people found painted out (finds
    # people the one-person detector skips; one more detector call per run; docs/
    # track_evaluation.md "Looking again")
    look_again: bool = True
    # blazepose: the second look also scans squares of this share of the frame's shorter side,
    # where people far at the back are larger (0: the usual windows only; docs/
    # track_evaluation.md "Small people at the back")
    look_again_zoom: float = Field(default=2 / 3, ge=0, lt=1)
    # blazepose: a person whose mask box's 32 x 32 thumbnail changed by at most this many grey
    # levels since their landmarks were computed keeps them (0: compute every frame; docs/
    # track_evaluation.md "People who stand still")
    still_change: float = Field(default=4.0, ge=0)
    # blazepose: processed frames a lost person's last region is looked at again, with everyone
    # tracked painted out (0: not; docs/track_evaluation.md "Lost behind someone")
    lost_retry: int = Field(default=10, ge=0)
    # blazepose: LiteRT threads per interpreter (results are identical for any number). None:
    # the cores each video tracked at once gets, at most 4 (one lab camera on 2 quiet cores:
    # 26.3 frames/s with 2 threads, 21.8 with 1; benchmarks/bench_track.py --real)
    detector_threads: int | None = Field(default=None, ge=1)
    overlay: bool = True  # write an overlay video per track (skeletons, boxes, ids)
    # move each body onto its confident 2D landmarks (translation only, gst.track.align)
    align_to_landmarks: bool = True
    # then fit each body's pose to its confident landmarks (gst.track.pose_fit;
    # docs/track_evaluation.md "Pose fit"). 'auto': for videos that are no calibrated camera of
    # the scene (`--video`), where the model has not seen the camera; true / false: every video
    # / none.
    fit_pose: Literal["auto"] | bool = "auto"
    # a video that is no calibrated camera of the scene: its lens's focal length as a 35 mm
    # equivalent (mm; a phone's spec sheet gives it), else the image diagonal (a 43 mm lens;
    # docs/track_evaluation.md "The focal length of an uncalibrated video")
    focal_35mm: float | None = Field(default=None, gt=0)
    # keep each person's left and right landmark labels continuous over time: BlazePose's
    # whole-body flips undone (gst.track.mirror; docs/track_evaluation.md "Left and right")
    unmirror: bool = True
    threads: PositiveInt | None = None  # torch threads; None: gst.track.scene.network_threads
    min_hits: PositiveInt = 3  # consecutive detections before a new person gets an id
    max_misses: NonNegativeInt = 30  # processed frames a person may go undetected and keep the id
    # Split videos longer than this many processed frames into chunks tracked in parallel and
    # stitched (gst/track/chunks.py); off by default because ids can differ where tracking is
    # ambiguous at a border. Not with smoothing or --with-gaussians.
    chunk_frames: int | None = Field(default=None, ge=1)
    chunk_overlap: int = Field(default=30, ge=1)  # frames two chunks share, to stitch ids
    # 'auto': pose-only crops with landmarks skip the network's image path when its learnt image
    # gate shows the image's share negligible (gst.model.inference.image_shapes_pose; same
    # accuracy at a quarter of the network's time, docs/track_evaluation.md); 'always': never skip
    image_path: Literal["auto", "always"] = "auto"
    # blazepose: keep the person model's detections of each video and replay them when the same
    # video is tracked again from its start with the same person model and settings (a new
    # network, other tracker settings): the model does not run again (gst.track.detection_cache)
    keep_detections: bool = True
    # where the network runs (gst.device): auto is the GPU when PyTorch sees one, else the CPU;
    # decoding, the person model and the pose fit stay on the CPU
    device: Annotated[str, AfterValidator(check_device_name)] = "auto"

    @model_validator(mode="after")
    def _chunks_do_not_smooth(self):
        if self.start_s is not None and self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end_s {self.end_s} must be after start_s {self.start_s}")
        # found only inside the run, after the stages before track had run (the filter's state
        # would restart at every chunk)
        if self.chunk_frames and self.smoothing:
            raise ValueError(
                "chunk_frames and smoothing do not go together (a chunk cannot carry the "
                "filter's state); turn one off"
            )
        return self


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
    scene: str | None = None  # the scene whose model (models/gst.pt) tracks the videos
    # where the person model's detections are kept between runs (gst.track.detection_cache)
    detections_cache: Path | None = None
    # the videos' frame rate where their headers are not to be trusted (the scene's `fps`, for
    # its own camera videos); None: each container's rate
    fps: float | None = None


def choose_detector(s: TrackSettings) -> tuple[str, str]:
    """(detector, why): 'boxes', 'blazepose' or 'background', and the reason, for the log and
    the file's `gst.detector`. A 'blazepose' that is not installed fails here, with the fix."""
    if s.boxes:
        return "boxes", f"boxes supplied in {s.boxes}"
    if s.detector == "background":
        return "background", "track.detector is 'background' (static-camera background model)"
    try:
        import_litert()
        model_paths()
    except (ImportError, BlazePoseModelsMissing) as exc:
        if s.detector == "blazepose":
            raise
        first = str(exc).strip().splitlines()[0]
        return "background", (
            f"the learned person model is not installed ({first}); the static-camera background "
            "model finds only people who move against a still background"
        )
    how = "track.detector is 'blazepose'" if s.detector == "blazepose" else "auto"
    return "blazepose", f"{how}: the learned person model (BlazePose) is installed"


def jobs_at_once(s: TrackSettings, workers: int, videos: int) -> int:
    """How many tracking jobs share the cores: videos, or with chunking their chunks (up to
    `workers` of them: one chunked video on 2 workers gave each chunk the threads of a video
    alone, 6 threads on 2 cores)."""
    return max(1, min(workers, workers if s.chunk_frames else videos))


def _cores_per_video(parallel_videos: int) -> int:
    return max(1, available_cores() // parallel_videos)


# track settings that are the learned person model's own, under the same names
PERSON_MODEL_SETTINGS = (
    "look_again",
    "look_again_zoom",
    "still_change",
    "lost_retry",
)


def detector_interval(s: TrackSettings, fps: float | None) -> int:
    """Processed frames between the person detector's runs for new arrivals in a video of
    `fps` frames per second (unknown: as at 30): `detect_every`, else `detect_every_s`."""
    if s.detect_every is not None:
        return s.detect_every
    rate = fps if fps and fps > 0 else 30.0
    return max(1, round(rate / s.stride * s.detect_every_s))


def person_model_config(
    s: TrackSettings, parallel_videos: int = 1, fps: float | None = None
) -> PersonModelConfig:
    """The learned person model's settings for `s` on a video of `fps` frames per second, with
    `parallel_videos` tracked at once."""
    threads = s.detector_threads or min(4, _cores_per_video(parallel_videos))
    return PersonModelConfig(
        threads=threads,
        detect_every=detector_interval(s, fps),
        # the detector sees video frame indices, `stride` apart: its gap is the default's
        # count of processed frames (else from stride 6 every frame restarted it)
        max_gap=PersonModelConfig.max_gap * s.stride,
        **{k: getattr(s, k) for k in PERSON_MODEL_SETTINGS},
    )


def network_threads(s: TrackSettings, kind: str, workers: int, parallel_videos: int) -> int | None:
    """torch threads for each video's network (None: leave torch's pool as it is).

    `track.threads` when set; one per worker when several videos share the cores. With the
    learned person model, which runs in its own thread beside the network, the network gets the
    cores the person model's LiteRT threads leave, at least one: on 2 cores two torch threads
    fighting the two LiteRT threads cost ~10 % of the frame rate on the lab capture (25.2 against
    23.1, 28.5 against 26.1 and 26.4 against 23.8 frames/s on cam01, cam02 and cam04)."""
    if s.threads:
        return s.threads
    if workers > 1:
        return 1
    if kind == "blazepose":
        cores = _cores_per_video(parallel_videos)
        return max(1, cores - person_model_config(s, parallel_videos).threads)
    return None


def _detector(
    kind: str,
    s: TrackSettings,
    video: Path,
    camera: Camera | None,
    rig: Rig | None,
    person_model: PersonModelConfig | None = None,
) -> Callable:
    """A picklable factory of the video's person detector: supplied boxes, the learned person
    model (with its settings for this video, `person_model`), or the static-camera background
    model."""
    if kind == "boxes":
        return functools.partial(SuppliedBoxes.from_file, s.boxes, video=video.stem)
    if kind == "blazepose":
        return functools.partial(PersonModelDetector, person_model)
    up = tuple(rig.up) if camera is not None else (0.0, 0.0, 1.0)
    return functools.partial(StaticCameraDetector, video, camera=camera, up=up)


def _video_rate(video: Path) -> float | None:
    """The video's frame rate, or None where it cannot be read (the video's own job then
    fails with the reason, naming it)."""
    try:
        return probe_video(video).fps
    except VideoError:
        return None


def _detector_info(
    kind: str, why: str, person_model: PersonModelConfig | None, boxes: Path | None = None
) -> dict:
    info = {"name": kind, "why": why}
    if boxes is not None:  # the boxes' content: an edited box file mixed into a resumed run and
        # kept a finished file of the old boxes (the info named the path alone)
        # (the whole file: an edit in its middle keeps the size and a sampled digest's ends)
        info["boxes_file"] = file_identity(boxes, whole=True)
    if person_model is not None:
        info["model"] = "MediaPipe BlazePose (pose_detection + pose_landmark_full), LiteRT"
        info["config"] = person_model.settings()
    return info


@dataclass(frozen=True)
class ModelProvenance:
    """What the tracks file (metadata `gst.model`) and the log say about the model: its name,
    checkpoint, body model, training mode, and what it was trained on as far as the checkpoint
    records it (`trained_on`: the checkpoint's own record, e.g. scene, cameras, frames, crops;
    {"scene", "recorded": False} when it has none)."""

    name: str
    version: str
    checkpoint: str
    body_model: str
    training_mode: str | None
    trained_on: dict
    # where the pose comes from: "landmarks" (crops with landmarks skip the image path, whose
    # share the network's image gate shows negligible; others use it) or "image and landmarks"
    pose_input: str = "image and landmarks"
    # rounds of reprojection feedback after the network's SMPL head (gst.model.refine; 0: none)
    reprojection_feedback: int = 0
    # the weights themselves: part of every tracks file's settings digest, so that tracks of
    # one checkpoint are never taken for another's (the path and version were constants)
    checkpoint_sha256: str | None = None

    def to_dict(self) -> dict:
        """The metadata's layout (the fields in order)."""
        return asdict(self)


def model_provenance(
    checkpoint: Path, name: str, scene: str | None, pose_input: str = "image and landmarks"
) -> ModelProvenance:
    """What the file and the log say about the model: name, checkpoint, and what it was trained
    on as far as the checkpoint records it (`extra.trained_on`: scene, cameras, frames)."""
    ckpt = load_checkpoint(checkpoint)
    extra = ckpt.extra
    trained_on = extra.get("trained_on")
    if not isinstance(trained_on, dict):
        trained_on = {"scene": scene, "recorded": False}
    return ModelProvenance(
        name=name,
        version="1",
        checkpoint="models/gst.pt",
        body_model=str(ckpt.body_model),
        training_mode=extra.get("mode"),
        trained_on=trained_on,
        pose_input=pose_input,
        reprojection_feedback=int(
            ckpt.config.get("landmark_refine", 0) if ckpt.config.get("landmark_tokens") else 0
        ),
        checkpoint_sha256=sha256_of(Path(checkpoint)),
    )


def _camera_seen(model: ModelProvenance, camera: Camera | None) -> bool:
    """Whether the model was trained on this video's camera (only a calibrated camera of the
    scene can be, and only when the checkpoint records its cameras)."""
    cams = model.trained_on.get("cameras")
    return camera is not None and isinstance(cams, list) and camera.name in cams


def _describe_training(t: dict) -> str:
    if not t.get("recorded", True):
        scene = f"scene '{t['scene']}'" if t.get("scene") else "an unknown scene"
        return f"{scene} (the checkpoint does not record which cameras and frames)"
    parts = [f"scene '{t.get('scene')}'"]
    if t.get("cameras") is not None:
        parts.append(f"cameras {', '.join(map(str, t['cameras']))}")
    if t.get("frames") is not None:
        parts.append(f"frames {t['frames']}")
    return ", ".join(parts)


def track_scene(
    s: TrackSettings,
    request: TrackRequest,
    *,
    map_fn: Callable | None = None,
    workers: int = 1,
) -> list[VideoOutcome]:
    """Track every video of the request and write its reports (see the module doc)."""
    check_unique_names([(v.stem, v) for v in request.videos])  # before the model loads
    images = [e for v in request.videos if (e := still_image_error(v)) is not None]
    if images:
        raise VideoError("; ".join(images))
    if s.boxes is not None and not Path(s.boxes).is_file():  # was a bare FileNotFoundError
        raise ValueError(f"track.boxes: no such file: {s.boxes} (looked for from {Path.cwd()})")
    if s.threads:
        torch.set_num_threads(s.threads)
    with_gaussians = request.splats_dir is not None
    # Load the model once here: a bad checkpoint fails now, naming the file, not in a worker.
    loaded = GSTPredictor(
        request.checkpoint,
        with_gaussians=with_gaussians,
        batch_size=s.batch_size,
        image_path=s.image_path,
    )
    name, pose_input = loaded.name, loaded.pose_input
    kind, why = choose_detector(s)  # a missing 'blazepose' fails here, not in a worker
    log.info("person detector: %s (%s)", kind, why)
    model_info = model_provenance(request.checkpoint, name, request.scene, pose_input)
    log.info(
        "model: %s, trained on %s; pose from %s (track.image_path: %s)%s",
        name,
        _describe_training(model_info.trained_on),
        pose_input,
        s.image_path,
        f", {model_info.reprojection_feedback} rounds of reprojection feedback"
        if model_info.reprojection_feedback
        else "",
    )
    options = TrackOptions(
        stride=s.stride,
        tracker=TrackerConfig(min_hits=s.min_hits, max_misses=s.max_misses),
        start_s=s.start_s,
        end_s=s.end_s,
        batch_size=s.batch_size,
        smoothing=OneEuroConfig(min_cutoff=s.min_cutoff, beta=s.beta) if s.smoothing else None,
        align=AlignmentConfig() if s.align_to_landmarks else None,
        unmirror=MirrorConfig() if s.unmirror else None,
        focal_35mm=s.focal_35mm,
        fps=request.fps,
    )
    parallel_videos = jobs_at_once(s, workers, len(request.videos))
    threads = network_threads(s, kind, workers, parallel_videos)
    device = str(resolve_device(s.device))
    log.info("network on %s (track.device: %s)", device, s.device)
    predictor = functools.partial(
        GSTPredictor,
        request.checkpoint,
        with_gaussians=with_gaussians,
        batch_size=s.batch_size,
        device=device,
        image_path=s.image_path,
    )
    rig = request.rig
    jobs = []
    for video in request.videos:
        camera = rig[video.stem] if rig is not None and video.stem in rig.names else None
        info = None
        if camera is not None:  # fitted to the frames now: a size mismatch fails here, named
            info = probe_video(video, camera.name)
            try:
                camera, note = fit_to_frames(
                    camera, info.width, info.height, request.frame_size_tolerance, str(video)
                )
            except CameraError as exc:  # its advice fits a calibration, not a file's name
                raise CameraError(
                    f"{exc} (this video is taken for the scene's calibrated camera "
                    f"'{camera.name}' because of its file name; rename it if it is another "
                    "camera's)"
                ) from exc
            if note:
                log.warning("%s", note)
        seen = _camera_seen(model_info, camera)
        if camera is None:
            log.info(
                "%s: not a calibrated camera of the scene: default pinhole camera (focal length ="
                " %s), camera-frame coordinates only, no world coordinates; the model has not "
                "seen this camera",
                video.stem,
                "image diagonal; set track.focal_35mm if the lens is known"
                if s.focal_35mm is None
                else f"{s.focal_35mm:g} mm, 35 mm equivalent (track.focal_35mm)",
            )
        elif s.focal_35mm is not None:
            log.info("%s: calibrated camera: track.focal_35mm is not used", video.stem)
        elif not seen:
            log.info("%s: calibrated camera; the model's training does not record it", video.stem)
        fit = camera is None if s.fit_pose == "auto" else bool(s.fit_pose)
        person_model = None
        if kind == "blazepose":
            rate = request.fps or (info.fps if info is not None else _video_rate(video))
            person_model = person_model_config(s, parallel_videos, rate)
            source = (
                "track.detect_every"
                if s.detect_every is not None
                else f"{rate:g} frames/s"
                if rate
                else "rate unknown: as at 30 frames/s"
            )
            log.info(
                "%s: the person detector looks for new arrivals every %d processed frame(s) "
                "(%s, stride %d, track.detect_every_s %.3g s)",
                video.stem, person_model.detect_every, source, s.stride, s.detect_every_s,
            )  # fmt: skip
        if fit:
            log.info("%s: poses are fitted to the landmarks where they disagree", video.stem)
        jobs.append(
            VideoJob(
                video,
                _detector(kind, s, video, camera, rig, person_model),
                predictor,
                {**model_info.to_dict(), "seen_this_camera": seen},
                name=video.stem,
                camera=camera,
                world_up=tuple(rig.up) if (rig is not None and camera is not None) else None,
                options=replace(options, pose_fit=PoseFitConfig() if fit else None),
                threads=threads,
                keep_extras=with_gaussians,
                detector_info=_detector_info(
                    kind, why, person_model, s.boxes if kind == "boxes" else None
                ),
                detections_cache=request.detections_cache
                if kind == "blazepose" and s.keep_detections
                else None,
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


def _write_contact_sheet(video: Path, tracks: Path, out: Path, n: int = 6) -> None:
    """Six processed frames with the tracks drawn on (boxes, ids, both skeletons), in a row."""
    frames = sorted(set(read_tracks(tracks).column("frame").to_pylist()))
    if not frames:
        return
    pick = [frames[round(i * (len(frames) - 1) / max(n - 1, 1))] for i in range(n)]
    sheet = np.concatenate(
        [contact_sheet(video, tracks, [f], height=480) for f in sorted(set(pick))], axis=1
    )
    atomic_write(out, lambda tmp: cv2.imwrite(str(tmp), sheet, [cv2.IMWRITE_JPEG_QUALITY, 85]))


@functools.lru_cache(maxsize=2)
def _body_and_markers(body_model: str) -> tuple[BodyModel, MarkerModel]:
    return load_body_model(body_model), MarkerModel.load()


def body_points_vs_landmarks(table, camera: Camera | None = None) -> LandmarkAgreement:
    """The rows' bodies' own BlazePose points (posed and projected with the camera the file was
    made with, else `camera` or the video's default one) against the landmarks: like with like
    (gst.track.agreement.markers_vs_landmarks)."""
    meta = parse_metadata(table.schema)
    video = meta["video"]
    if "K" in (meta.get("calibration") or {}):  # the camera the file was made with
        view = TrackingView.from_json(meta["calibration"])
    else:
        view = TrackingView.for_video(video["width"], video["height"], camera, video["name"])
    body, markers = _body_and_markers(meta["model"].get("body_model", "anny"))
    return markers_vs_landmarks(table, body_markers_2d(table, body, markers, view.project))


def _landmark_agreement(table, camera: Camera | None, name: str) -> dict:
    """The summary's two checks of the body against the landmark model's joints: its joints
    (`joints2d`), and its own BlazePose points (like with like; gst.track.agreement)."""
    agree = joints_vs_landmarks(table)
    out = {"joints2d_vs_landmarks": agree.to_dict()}
    if agree.median_px is None:
        return out
    same = body_points_vs_landmarks(table, camera)
    out["body_landmarks_vs_landmarks"] = same.to_dict()
    log.info(
        "%s: the body's joints lie a median %.1f px (90%%: %.1f px) from the landmark model's, "
        "its own BlazePose points %.1f px (%d joints compared)",
        name, agree.median_px, agree.p90_px, same.median_px, agree.pairs,
    )  # fmt: skip
    return out


def nobody_tracked(rows: int, frames: int, s: TrackSettings) -> str | None:
    """Why a video's tracks are empty (None: they are not). An empty Parquet reads as a result
    like any other: a 2-frame clip at `min_hits` 3 gave 0 rows, exit 0 and no word."""
    if rows:
        return None
    if frames < s.min_hits:  # `frames` counts processed frames
        return (
            f"nobody was tracked in {frames} frame(s): a person needs track.min_hits="
            f"{s.min_hits} processed frames in a row to get an id"
        )
    return f"nobody was tracked in {frames} frame(s): the person detector kept no one"


def write_video_report(
    s: TrackSettings, request: TrackRequest, outcome: VideoOutcome
) -> TrackEvaluation | None:
    """Summary, overlay video, joint-angle plot and splats of one tracked video; its evaluation
    against the truth when it is a synthetic scene's camera."""
    name, result = outcome.job.name, outcome.result
    # A finished file kept from an earlier, interrupted run of the stage took no tracking in
    # this one: its time is not this run's (it read as 7934 frames/s), so no speed is claimed.
    kept = result.kept_finished
    fps = None if kept else result.frames / max(result.seconds, 1e-9)
    summary = {
        "rows": result.rows,
        "frames": result.frames,
        "persons": result.persons,
        "seconds": None if kept else round(result.seconds, 2),
        "fps": None if fps is None else round(fps, 2),
        "kept_from_earlier_run": kept,
        "calibrated": outcome.job.camera is not None,
        "chunks": outcome.chunks,
        "person_detections": result.detections,
    }
    table = read_tracks(result.path)
    # detections whose left/right labels were exchanged (track.unmirror, gst.track.mirror)
    stats = parse_metadata(table.schema).get("stats") or {}
    summary["landmarks_exchanged"] = int(stats.get("landmarks_exchanged", 0))
    log.info(
        "%s: %d frames, %d people, %s (person detector: %s); left/right labels "
        "exchanged in %d detection(s)",
        name,
        result.frames,
        result.persons,
        "kept from an earlier run" if fps is None else f"{fps:.1f} frames/s",
        result.detections,
        summary["landmarks_exchanged"],
    )
    if (why := nobody_tracked(result.rows, result.frames, s)) is not None:
        log.warning("%s: %s", name, why)
    summary.update(_landmark_agreement(table, outcome.job.camera, name))
    report = request.reports_dir / name
    report.mkdir(parents=True, exist_ok=True)
    atomic_write_text(report / "summary.json", json.dumps(summary, indent=2))
    if s.overlay:
        write_overlay(outcome.job.video, result.path, report / "overlay.mp4")
    _write_contact_sheet(outcome.job.video, result.path, report / "contact_sheet.jpg")
    plot_joint_angles(result.path, report / "joint_angles.png")
    evaluation = _evaluate(request, outcome, report)
    if request.splats_dir is not None:  # the stage's declared output, empty when nobody was
        # tracked (it was made only by a first splat: the stage then failed, "did not write")
        (request.splats_dir / name).mkdir(parents=True, exist_ok=True)
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
