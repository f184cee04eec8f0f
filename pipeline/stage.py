"""What a stage is: a thin recipe with declared outputs, external inputs and typed params.

A stage module in `stages/` defines `STAGE = Stage(...)`. The runner gives `run` a
`StageContext`; the stage writes every declared output under `ctx.staging` (same relative
layout as the scene workspace) and reads upstream outputs from `ctx.workspace`. The runner
moves the outputs into place only after `run` returns, then records the fingerprint.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict

from calibration import Rig
from calibration.formats import read_rig
from pipeline.config import PipelineConfig, SceneConfig

T = TypeVar("T")

# a scene's folder of the landmark model's readings of crowded crops, shared by the fuse stage
# and train's rig teacher (gst.detect.reading_cache)
READINGS = ".pipeline/cache/readings"


class StageParams(BaseModel):
    """Base for a stage's parameters: unknown keys are errors, and so are NaN and infinity."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


@dataclass
class StageContext:
    stage: str
    scene_name: str
    scene: SceneConfig
    config: PipelineConfig
    workspace: Path  # the scene's workspace (final outputs of all stages)
    staging: Path  # where this run writes its outputs; moved into `workspace` on success
    params: Any  # the stage's validated StageParams
    options: dict[str, Any] = field(default_factory=dict)  # stage-specific CLI options (e.g. video)
    executor: Any = None  # pipeline.executors.Executor
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("pipeline"))
    progress: Callable[..., Iterator] | None = None
    resumed: bool = False  # staging held a partial run with the same fingerprint

    def out(self, rel: str | Path) -> Path:
        """Path of an output inside the staging area (parent folders are created)."""
        p = self.staging / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def path(self, rel: str | Path) -> Path:
        """Path of an existing artefact in the scene workspace (an upstream stage's output)."""
        return self.workspace / rel

    def camera_videos(self) -> dict[str, Path]:
        """The scene's camera videos by camera name (the file stem), sorted: a synthetic scene's
        rendered `synth/videos/*.mp4`, or the files the scene's `videos` names."""
        if self.scene.is_synthetic:
            files = sorted(self.path("synth/videos").glob("*.mp4"))
        else:
            files = self.scene.video_files()
        return {p.stem: p for p in files}

    def background_plates(
        self, videos: dict[str, Path] | None, use_board_clip: bool
    ) -> dict[str, Path] | None:
        """Clips of the empty scene per camera, to learn the background from: `videos` when
        given, else a synthetic scene's board clips (an empty stage) when `use_board_clip`;
        None: learn it from the camera videos themselves."""
        if videos is None and self.scene.is_synthetic and use_board_clip:
            return {n: self.path(f"synth/board/{n}.mp4") for n in self.camera_videos()}
        return videos

    def input_videos(self, background_videos: dict[str, Path] | None = None) -> list[Path]:
        """The files outside the workspace a stage reads videos from (its fingerprint covers
        them): a real scene's camera videos and the given clips of the empty scene."""
        files = [] if self.scene.is_synthetic else list(self.scene.video_files())
        return files + list((background_videos or {}).values())

    def rig(self) -> Rig:
        """The scene's calibrated rig (`calibration/rig.json`, written by the calibrate stage)."""
        return read_rig(self.path("calibration/rig.json"), "rig")

    def track(self, items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
        """Iterate with a progress bar (quiet runs just iterate)."""
        if self.progress is None:
            yield from items
        else:
            yield from self.progress(items, description=description, total=total)


@dataclass(frozen=True)
class Stage:
    """A DAG step. `outputs` and `inputs` may depend on the context (e.g. track's --video)."""

    name: str
    run: Callable[[StageContext], None]
    outputs: Callable[[StageContext], list[str]]
    params_model: type[StageParams] = StageParams
    inputs: Callable[[StageContext], list[Path]] = lambda ctx: []
    applies: Callable[[SceneConfig], bool] = lambda scene: True
    variant: Callable[[StageContext], str | None] = lambda ctx: None
    version: str = "1"  # bump when the stage's outputs change meaning
    resumable: bool = False  # keep a killed run's staging folder and let `run` continue it
    help: str = ""
    cli_options: tuple[str, ...] = ()  # names of CLI options the stage reads from ctx.options
    in_all: bool = True  # False: `run all` skips it; it runs when named (e.g. a benchmark sweep)
    # False: the stage reads nothing of the scene's own settings (its footage, rate, masks), so
    # editing them does not make it stale (pretrain trains on worlds of its own)
    reads_scene: bool = True
