"""calibrate: import the scene's calibration file, or solve the rig from board footage (a
synthetic scene: its rendered ChArUco clip, the real code path, compared with its truth).
Writes `calibration/rig.json` (docs/formats/rig_json.md) and `reports/calibrate/`; library:
`calibration.scene.calibrate_scene`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import NonNegativeInt, PositiveInt

from calibration.board import BoardSpec
from calibration.scene import BoardFootage, CalibrationFile, SolveSettings, calibrate_scene
from pipeline.stage import Stage, StageContext, StageParams

SYNTH_FILES = {"rig": "rig.json", "panoptic": "calibration_synth.json", "h36m": "cameras.h5"}


class Params(StageParams):
    # synthetic scenes: solve the rig from the rendered board clips, or read the scene's file
    synthetic_source: Literal["board", "rig", "panoptic", "h36m"] = "board"
    frame_step: PositiveInt = 1  # search every Nth frame of the board clips
    max_frames: PositiveInt | None = None  # cap on board frames searched per camera
    floor_world: bool = True  # world from the board's floor pose: z up, floor z = 0, metres
    strict_checks: bool = True  # refuse rigs that fail check_rig (floor, aim, lens model)
    floor_frame: NonNegativeInt | None = None  # the board frame that sets the floor (None: first)
    # every camera's lens: pinhole, opencv (k1 k2 p1 p2) or full_opencv (+ k3-k6, wide angle)
    lens_model: Literal["pinhole", "opencv", "full_opencv"] = "opencv"
    ba_max_iterations: PositiveInt = 100  # per bundle adjustment round (a note says if it stops)


def _sources(ctx: StageContext) -> tuple[CalibrationFile | None, BoardFootage | None]:
    scene, p = ctx.scene, ctx.params
    if scene.calibration is not None:
        c = scene.calibration
        return CalibrationFile(c.file, c.format, c.options), None
    if scene.is_synthetic and p.synthetic_source != "board":
        file = ctx.path("synth/calibration") / SYNTH_FILES[p.synthetic_source]
        return CalibrationFile(file, p.synthetic_source), None
    if scene.is_synthetic:
        spec = BoardSpec.from_dict(json.loads(ctx.path("synth/board.json").read_text()))
        return None, BoardFootage(
            {v.stem: v for v in sorted(ctx.path("synth/board").glob("*.mp4"))}, spec
        )
    if scene.board is None:
        return None, None  # calibrate_scene says what to add
    b = scene.board
    videos = scene.board_videos()
    if not videos:
        raise FileNotFoundError(
            f"scene '{ctx.scene_name}': board.videos matched no files ({b.videos})"
        )
    spec = BoardSpec(b.kind, b.squares_x, b.squares_y, b.square_size, b.marker_size, b.dictionary)
    return None, BoardFootage({Path(v).stem: Path(v) for v in videos}, spec)


def run(ctx: StageContext) -> None:
    file, footage = _sources(ctx)
    truth = ctx.path("synth/calibration/rig.json") if ctx.scene.is_synthetic else None
    calibrate_scene(
        ctx.camera_videos(), ctx.out("calibration/rig.json"), ctx.out("reports/calibrate"),
        file=file, footage=footage, truth_rig=truth, scene=ctx.scene_name,
        settings=SolveSettings(**ctx.params.model_dump(exclude={"synthetic_source"}),
                               frame_size_tolerance=ctx.scene.frame_size_tolerance),
    )  # fmt: skip


def _inputs(ctx: StageContext) -> list[Path]:
    own = [ctx.scene.calibration.file] if ctx.scene.calibration else ctx.scene.board_videos()
    return own + ctx.input_videos()  # the rig is fitted to their frame size, checked against them


STAGE = Stage(
    name="calibrate", run=run, params_model=Params, inputs=_inputs,
    outputs=lambda ctx: ["calibration", "reports/calibrate"],
    help="import the scene's calibration file, or solve the rig from ChArUco/checkerboard footage",
)  # fmt: skip
