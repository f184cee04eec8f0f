"""calibrate: import the scene's calibration file, or solve the rig from board footage.

Writes `calibration/rig.json` (docs/formats/rig_json.md) and `reports/calibrate/`. A scene that
supplies a calibration file is imported and checked, never re-solved. A synthetic scene is
solved from its rendered ChArUco clip by default (the real code path) and the report compares
the solved rig with the scene's true rig.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from calibration.board import BoardSpec
from calibration.checks import check_rig
from calibration.compare import compare_rigs
from calibration.formats import read_rig, write_rig
from calibration.report import write_calibration_report
from calibration.solve import calibrate_from_board
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    synthetic_source: Literal["board", "rig", "panoptic", "h36m"] = "board"
    frame_step: int = 1  # search every Nth frame of the board clips
    max_frames: int | None = None  # cap on board frames searched per camera
    floor_world: bool = True  # world from the board's floor pose: z up, floor z = 0, metres
    strict_checks: bool = True  # refuse rigs whose cameras sit below the floor or look away


SYNTH_FILES = {"rig": "rig.json", "panoptic": "calibration_synth.json", "h36m": "cameras.h5"}


def _board_sources(ctx: StageContext) -> tuple[dict[str, Path], BoardSpec]:
    if ctx.scene.is_synthetic:
        spec = BoardSpec.from_dict(json.loads(ctx.path("synth/board.json").read_text()))
        return {p.stem: p for p in sorted(ctx.path("synth/board").glob("*.mp4"))}, spec
    b = ctx.scene.board
    videos = (
        b.videos
        if isinstance(b.videos, list)
        else sorted(Path(p) for p in __import__("glob").glob(b.videos))
    )
    if not videos:
        raise FileNotFoundError(
            f"scene '{ctx.scene_name}': board.videos matched no files ({b.videos})"
        )
    spec = BoardSpec(
        kind=b.kind,
        squares_x=b.squares_x,
        squares_y=b.squares_y,
        square_size=b.square_size,
        marker_size=b.marker_size,
        dictionary=b.dictionary,
    )
    return {Path(v).stem: Path(v) for v in videos}, spec


def _scene_videos(ctx: StageContext) -> dict[str, Path]:
    if ctx.scene.is_synthetic:
        return {p.stem: p for p in sorted(ctx.path("synth/videos").glob("*.mp4"))}
    return {p.stem: p for p in ctx.scene.video_files()}


def _first_frames(videos: dict[str, Path]) -> dict[str, np.ndarray]:
    frames = {}
    for name, path in videos.items():
        cap = cv2.VideoCapture(str(path))
        ok, frame = cap.read()
        cap.release()
        if ok:
            frames[name] = frame
    return frames


def run(ctx: StageContext) -> None:
    p = ctx.params
    solved, truth = None, None
    if ctx.scene.calibration is not None:
        c = ctx.scene.calibration
        rig = read_rig(c.file, c.format, **c.options)
        ctx.log.info("imported %d cameras from %s", len(rig), c.file)
    elif ctx.scene.is_synthetic and p.synthetic_source != "board":
        rig = read_rig(
            ctx.path("synth/calibration") / SYNTH_FILES[p.synthetic_source], p.synthetic_source
        )
    elif ctx.scene.is_synthetic or ctx.scene.board is not None:
        sources, board = _board_sources(ctx)
        step_log = {}

        def progress(step: str, done: int, total: int) -> None:
            if done == total or step not in step_log:
                step_log[step] = done
                ctx.log.info("%s: %d/%d", step, done, total)

        solved = calibrate_from_board(
            sources,
            board,
            frame_step=p.frame_step,
            max_frames=p.max_frames,
            floor_world=p.floor_world,
            progress=progress,
        )
        rig = solved.rig
        ctx.log.info(
            "board calibration: RMS %s px", {k: round(v, 3) for k, v in solved.rms_px.items()}
        )
        if ctx.scene.is_synthetic:
            truth = read_rig(ctx.path("synth/calibration/rig.json"), "rig")
    else:
        raise ValueError(
            f"scene '{ctx.scene_name}' has neither a calibration file nor board footage: add "
            "'calibration: {file: ..., format: ...}' or 'board: {...}' to the scene in pipeline.yaml"
        )

    videos = _scene_videos(ctx)
    missing = [name for name in videos if name not in rig.names]
    if missing:
        raise ValueError(
            f"scene '{ctx.scene_name}': videos {missing} have no camera of that name in the "
            f"calibration (cameras: {rig.names}); rename the files or the cameras"
        )
    problems = check_rig(rig)
    if problems and p.strict_checks:
        raise ValueError(
            f"scene '{ctx.scene_name}': the rig failed its checks and was not written: "
            + "; ".join(problems)
            + " (set calibrate.strict_checks=false to accept it)"
        )
    for problem in problems:
        ctx.log.warning("rig check: %s", problem)

    write_rig(rig, ctx.out("calibration/rig.json"), "rig")
    report_dir = ctx.out("reports/calibrate")
    report = write_calibration_report(
        rig, report_dir, calibration=solved, frames=_first_frames(videos)
    )
    if truth is not None:
        _append_truth_comparison(ctx, report, compare_rigs(rig, truth))


def _append_truth_comparison(ctx: StageContext, report: Path, cmp) -> None:
    rows = cmp.as_rows()
    lines = [
        "",
        "## Against the synthetic truth",
        "",
        f"Rig diameter {cmp.rig_diameter_m:.2f} m. Errors after aligning camera centres (no scale fitted).",
        "",
        "| camera | focal error % | centre error mm | rotation error deg |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['camera']} | {100 * r['focal_rel_error']:.3f} | {1000 * r['center_error_m']:.1f} | "
        f"{r['rotation_error_deg']:.3f} |"
        for r in rows
    ]
    with open(report, "a") as f:
        f.write("\n".join(lines) + "\n")
    (report.parent / "truth_comparison.json").write_text(json.dumps(rows, indent=2))
    ctx.log.info(
        "against truth: focal %.3f%%, centre %.1f mm, rotation %.3f deg (worst camera)",
        100 * cmp.focal_rel_error.max(),
        1000 * cmp.center_error_m.max(),
        cmp.rotation_error_deg.max(),
    )


def _inputs(ctx: StageContext) -> list[Path]:
    if ctx.scene.calibration is not None:
        return [ctx.scene.calibration.file]
    if ctx.scene.board is not None and not ctx.scene.is_synthetic:
        return list(_board_sources(ctx)[0].values())
    return []


STAGE = Stage(
    name="calibrate",
    run=run,
    params_model=Params,
    inputs=_inputs,
    outputs=lambda ctx: ["calibration", "reports/calibrate"],
    help="import the scene's calibration file, or solve the rig from ChArUco/checkerboard footage",
)
