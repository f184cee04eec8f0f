"""Calibrate one scene: import its calibration file or solve the rig from board footage, check
the rig against the scene's videos, and write `rig.json` with a report.

A scene that supplies a calibration file is imported and checked, never re-solved. Board
footage (ChArUco or checkerboard, one video or image folder per camera) is solved with bundle
adjustment (`calibration.solve`). Given the true rig (synthetic scenes), the report compares
the solved one with it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.board import BoardSpec
from calibration.bundle import BAOptions
from calibration.camera import FRAME_PADDING_TOLERANCE, Rig, fit_rig_to_frames
from calibration.checks import check_rig, lens_warnings
from calibration.compare import RigComparison, compare_rigs
from calibration.formats import read_rig, write_rig
from calibration.report import write_calibration_report
from calibration.solve import BoardCalibration, SolveOptions, calibrate_from_board
from gst.atomic import atomic_write_json
from gst.video import VideoError, differing_rates, probe_video, probe_videos, read_frames

log = logging.getLogger("calibration")


@dataclass(frozen=True)
class CalibrationFile:
    path: Path
    format: str | None = None  # auto-detected when None
    options: dict[str, Any] | None = None


@dataclass(frozen=True)
class BoardFootage:
    sources: dict[str, Path]  # camera name -> board video or image folder
    board: BoardSpec


@dataclass(frozen=True)
class SolveSettings:
    frame_step: int = 1  # search every Nth frame of the board clips
    max_frames: int | None = None  # cap on board frames searched per camera
    floor_world: bool = True  # world from the board's floor pose: z up, floor z = 0, metres
    strict_checks: bool = True  # refuse rigs that fail check_rig (floor, aim, lens model)
    frame_size_tolerance: int = FRAME_PADDING_TOLERANCE  # encoder padding accepted, in pixels
    floor_frame: int | None = None  # the frame whose board lies on the floor (None: the first)
    lens_model: str = "opencv"  # SolveOptions.lens_model: pinhole, opencv or full_opencv
    ba_max_iterations: int = 100  # BAOptions.max_iterations, per bundle adjustment round


@dataclass
class SceneCalibration:
    """What `calibrate_scene` wrote and found."""

    rig: Rig
    rig_path: Path
    report: Path
    solved: BoardCalibration | None = None
    problems: tuple[str, ...] = ()
    against_truth: RigComparison | None = None
    frame_size_notes: tuple[str, ...] = ()  # cameras fitted to their videos' frame size


def first_frames(videos: dict[str, Path]) -> dict[str, np.ndarray]:
    """The first frame of every readable video (the report's floor-grid overlays)."""
    frames = {}
    for name, path in videos.items():
        try:
            for _, image in read_frames(path, [0], name):
                frames[name] = image
        except VideoError as exc:
            log.warning("calibration report: no overlay for camera '%s': %s", name, exc)
    return frames


def _check_board_rates(sources: dict[str, Path], scene: str) -> None:
    """Refuse board videos of different frame rates before detection: the solve pairs the
    cameras' board views by frame index, so at another rate it paired views of different
    instants (a wrong rig, or a failure deep in the solve naming a camera's focal length).
    Image folders and files the probe cannot read are left to the detection."""
    infos = {}
    for name, path in sources.items():
        if Path(path).is_file():
            try:
                infos[name] = probe_video(path, name, strict=True)
            except VideoError:
                continue
    rates = differing_rates(infos)
    if rates:
        raise ValueError(
            f"scene '{scene}': the board videos have different frame rates ({rates} frames/s); "
            "the calibration pairs the cameras' board views by frame index, so it expects "
            "synchronised board videos of one rate: record or re-encode them at one rate"
        )


def fit_rig_to_videos(
    rig: Rig, videos: dict[str, Path], tolerance: int = FRAME_PADDING_TOLERANCE
) -> tuple[Rig, list[str]]:
    """Every camera fitted to its video's decoded frame size (`fit_rig_to_frames`)."""
    return fit_rig_to_frames(
        rig, probe_videos({c.name: videos[c.name] for c in rig if c.name in videos}), tolerance
    )


def _size_section(notes: list[str]) -> list[str]:
    if not notes:
        return []
    return ["", "## Frame sizes adjusted to the videos", ""] + [f"- {n}" for n in notes]


def _truth_section(cmp: RigComparison) -> list[str]:
    lines = [
        "",
        "## Against the synthetic truth",
        "",
        f"Rig diameter {cmp.rig_diameter_m:.2f} m. "
        "Errors after aligning camera centres (no scale fitted).",
        "",
        "| camera | focal error % | centre error mm | rotation error deg |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['camera']} | {100 * r['focal_rel_error']:.3f} | "
        f"{1000 * r['center_error_m']:.1f} | {r['rotation_error_deg']:.3f} |"
        for r in cmp.as_rows()
    ]
    return lines


def _progress_logger():
    seen: dict[str, int] = {}

    def progress(step: str, done: int, total: int) -> None:
        if done == total or step not in seen:
            seen[step] = done
            log.info("%s: %d/%d", step, done, total)

    return progress


def calibrate_scene(
    videos: dict[str, Path],
    rig_path: Path,
    report_dir: Path,
    *,
    file: CalibrationFile | None = None,
    footage: BoardFootage | None = None,
    settings: SolveSettings = SolveSettings(),
    truth_rig: Path | None = None,
    scene: str = "scene",
) -> SceneCalibration:
    """Import `file` or solve from `footage` (exactly one), check the rig (every video needs a
    camera of its name; floor and aim checks), write `rig_path` and the report in `report_dir`.
    `truth_rig`: a rig.json to compare a solved rig with. Errors name the scene and the fix."""
    if (file is None) == (footage is None):
        raise ValueError(
            f"scene '{scene}' needs exactly one of a calibration file or board footage: add "
            "'calibration: {file: ..., format: ...}' or 'board: {...}' to the scene"
        )
    if footage is not None and not footage.sources:
        raise ValueError(
            f"scene '{scene}': no board footage to solve the rig from; a synthetic scene "
            "rendered without a board clip (synth board.n_frames: 0) can import its own "
            "calibration instead: calibrate.synthetic_source rig, panoptic or h36m"
        )
    solved = None
    if file is not None:
        rig = read_rig(file.path, file.format, **(file.options or {}))
        log.info("imported %d cameras from %s", len(rig), file.path)
    else:
        _check_board_rates(footage.sources, scene)
        solved = calibrate_from_board(
            footage.sources,
            footage.board,
            frame_step=settings.frame_step,
            max_frames=settings.max_frames,
            floor_world=settings.floor_world,
            floor_frame=settings.floor_frame,
            options=SolveOptions(
                lens_model=settings.lens_model,
                ba=BAOptions(max_iterations=settings.ba_max_iterations),
            ),
            progress=_progress_logger(),
        )
        rig = solved.rig
        rms = {k: round(v, 3) for k, v in solved.rms_px.items()}
        log.info("board calibration: RMS %s px", rms)
    missing = [name for name in videos if name not in rig.names]
    if missing:
        skipped = rig.meta.get("skipped") or []
        passed_over = [s for s in skipped if s.split(" ")[0] in missing]
        if passed_over:  # in the file, but the reader's options passed them over
            raise ValueError(
                f"scene '{scene}': videos {missing} have no camera in the calibration as read: "
                f"{file.path} holds {', '.join(passed_over)}, passed over by the reader's "
                f"options; keep them with scenes.{scene}.calibration.options (e.g. "
                "include_inactive: true, video_only: false)"
            )
        raise ValueError(
            f"scene '{scene}': videos {missing} have no camera of that name in the "
            f"calibration (cameras: {rig.names}); rename the files or the cameras, or leave "
            f"the videos out of scenes.{scene}.videos"
        )
    unseen = [name for name in rig.names if name not in videos]
    if unseen and videos:
        # a camera left out of the scene's video list fuses nothing from it: with the lab's
        # cam04 left out, extraction split the man into two ids, without a word
        log.warning(
            "calibration: cameras %s have no video in the scene (videos: %s); they are kept in "
            "the rig but see nothing: list their videos in scenes.%s.videos if they recorded",
            unseen, sorted(videos), scene,
        )  # fmt: skip
    problems = check_rig(rig)
    for warning in lens_warnings(rig):  # a lens model poorly held near the border: said only
        log.warning("rig check: %s", warning)
    if solved is not None:
        flagged = {**solved.weak_cameras, **solved.suspect_cameras}
        weak = [n for n in solved.notes if any(f"camera '{c}'" in n for c in flagged)]
        for note in solved.notes:
            if note not in weak:  # the weak cameras' notes are logged with the rig checks
                log.warning("calibration: %s", note)
        problems += weak
    if problems and settings.strict_checks:
        raise ValueError(
            f"scene '{scene}': the rig failed its checks and was not written: "
            + "; ".join(problems)
            + " (set calibrate.strict_checks=false to accept it)"
        )
    rig, size_notes = fit_rig_to_videos(rig, videos, settings.frame_size_tolerance)
    for problem in problems:
        log.warning("rig check: %s", problem)
    write_rig(rig, rig_path, "rig")
    cmp = None
    truth = read_rig(truth_rig, "rig") if truth_rig is not None and solved is not None else None
    if truth is not None and len(set(truth.names) & set(rig.names)) < 3:
        log.info("against truth: fewer than 3 shared cameras, no rigid alignment to compare by")
    elif truth is not None:
        cmp = compare_rigs(rig, truth)
        log.info(
            "against truth: focal %.3f%%, centre %.1f mm, rotation %.3f deg (worst camera)",
            100 * cmp.focal_rel_error.max(),
            1000 * cmp.center_error_m.max(),
            cmp.rotation_error_deg.max(),
        )
    report = write_calibration_report(
        rig,
        report_dir,
        calibration=solved,
        frames=first_frames(videos),
        appendix=_size_section(size_notes) + (_truth_section(cmp) if cmp is not None else []),
    )
    if cmp is not None:
        atomic_write_json(report_dir / "truth_comparison.json", cmp.as_rows())
    return SceneCalibration(rig, rig_path, report, solved, tuple(problems), cmp, tuple(size_notes))
