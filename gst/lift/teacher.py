"""The rig as teacher: the fuse stage's fusion of the crops' landmarks, without held-out data.

`RigTeacher(fused, crops_h5, rig)` is a `gst.train.distill.Teacher`: called with the crops'
landmarks and the rows training may use, it returns the fuse stage's own bodies when every row
may be used, else the same fusion (`gst.fuse.fuse_scene`, with the settings the fuse stage
recorded in its file) run on a copy of the crop store that holds the allowed rows only
(`gst.data.store.write_subset`), with their landmarks. Nothing of a held-out camera or frame
reaches the fusion: not its landmarks, nor its pixels (the crowded crops read again, the
people's silhouettes that vote in the triangulation), so none informs a target
(tests/test_train_distill.py). Of the store it is given: crops cut from the fuse stage's bodies
(`train.crops: bodycrops`) were shaped by bodies fitted on every camera and frame (docs/fuse.md).
Until 2026-11-30 the fusion ran on the whole store with the
held-out rows' landmarks removed, and its second reading of crowded crops read the held-out
crops' pixels again (the demo: 190 of 216 held-out crops).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gst.data.store import CropStore, write_subset
from gst.fuse import FuseOptions, fuse_scene
from gst.fuse.tables import FusedBodies, read_fused_bodies

log = logging.getLogger("gst.train")

__all__ = ["RigTeacher", "fuse_options"]


def _build(cls, recorded: dict):
    """An options dataclass from its recorded JSON: nested option dataclasses are rebuilt,
    fields this version does not know are ignored, missing ones keep their defaults."""
    defaults = cls()
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in recorded:
            continue
        value, default = recorded[f.name], getattr(defaults, f.name)
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = _build(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


def fuse_options(settings: dict) -> FuseOptions:
    """The fuse stage's FuseOptions from the settings its file records (no overlay videos)."""
    return dataclasses.replace(_build(FuseOptions, settings), overlay=False)


@dataclass(frozen=True)
class RigTeacher:
    fused: Path  # the fuse stage's fused/bodies.parquet
    crops_h5: Path  # the crop store the landmarks' rows belong to
    rig: object  # the calibration (calibration.camera.Rig)
    # where the landmark model's readings of crowded crops are kept (gst.detect.reading_cache):
    # the fuse stage read the same crops; None: read again
    reading_cache: Path | None = None

    def __call__(
        self, landmarks: np.ndarray, allowed: np.ndarray, work: Path, *, refit: bool = False
    ) -> FusedBodies:
        """The bodies fused from the `allowed` rows' `landmarks` (per row of the crop store).
        With every row allowed and the landmarks as the fuse stage read them, those are its
        own bodies; `refit` says the landmarks were changed (un-mirrored), so the bodies are
        fitted again even then (with nothing held out, the correction was otherwise lost)."""
        bodies = read_fused_bodies(self.fused)
        if bool(np.all(allowed)) and not refit:
            return bodies
        work = Path(work)
        work.mkdir(parents=True, exist_ok=True)
        rows = np.flatnonzero(allowed)
        store = write_subset(CropStore(self.crops_h5), rows, work / "allowed.h5")
        with warnings.catch_warnings():  # rows without landmarks: empty means in the report
            warnings.simplefilter("ignore", RuntimeWarning)
            warnings.simplefilter("ignore", UserWarning)
            result = fuse_scene(
                store.path,
                self.rig,
                work / "fused",
                work / "report",
                fps=bodies.fps,
                options=fuse_options(bodies.settings),
                landmarks=np.asarray(landmarks, np.float32)[rows],
                reading_cache=self.reading_cache,
            )
        log.info(
            "distill: teacher refitted on %d of %d crops (held-out cameras and frames removed%s)",
            int(np.sum(allowed)),
            len(allowed),
            ", landmarks un-mirrored" if refit else "",
        )
        return read_fused_bodies(result.bodies)
