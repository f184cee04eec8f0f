"""The fuse stage's recipe: fuse the extraction's crops, then cut the crops again from the
fitted bodies and fuse again on those, `rounds` times; last, cut the crops from the final
bodies for the user and for training (docs/fuse.md "Crops from the fitted bodies").

Crops cut from the bodies carry the fused ids in every camera, a crop in every view that shows
the person (read again where others crowd it), and masks nearer the truth, so the second fusion
sees its people more completely and paints the others out more exactly: on the six crowd
scenes the fused error fell from 50.1 to 44.4 mm (docs/fuse.md). Every cut takes its
landmarks and extra foreground from the extraction's store, never from an earlier cut. A
resumed run starts again from the first fusion's fit (each fusion removes its work folder when
it finishes, and each cut is written anew).
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

from calibration.camera import Rig
from gst.fuse.body_crops import BodyCropOptions, BodyCropReport, recut_crops, write_body_crop_report
from gst.fuse.scene import FuseOptions, FuseResult, fuse_scene

__all__ = ["FuseRounds", "fuse_rounds"]


@dataclass
class FuseRounds:
    fused: FuseResult  # the last fusion
    crops: BodyCropReport  # the crops cut from its bodies


def fuse_rounds(
    crops_h5: Path,
    rig: Rig,
    out_dir: Path,
    report_dir: Path,
    crops_out: Path,
    crops_report_dir: Path,
    *,
    rounds: int = 1,
    fps: float | None = None,
    options: FuseOptions | None = None,
    crop_options: BodyCropOptions | None = None,
    videos: dict[str, Path],
    plates: dict[str, Path] | None = None,
    truth_dir: Path | None = None,
    progress=None,
    log=None,
) -> FuseRounds:
    """Fuse `crops_h5` (the extraction's store) into `out_dir` / `report_dir` after `rounds`
    rounds of cutting the crops again from the bodies and fusing those; the crops cut from the
    final bodies go to `crops_out` (report in `crops_report_dir`). `videos` and `plates`
    (clean plates, None: the background is learnt from the videos) are per camera."""
    options = options or FuseOptions()
    work = out_dir.parent / f".{out_dir.name}.rounds"
    store = crops_h5
    quiet = dataclasses.replace(options, overlay=False)
    for r in range(rounds + 1):
        last = r == rounds
        where = (out_dir, report_dir) if last else (work / f"fused_{r}", work / f"report_{r}")
        result = fuse_scene(
            store, rig, *where, fps=fps, options=options if last else quiet,
            truth_dir=truth_dir, videos=videos, progress=progress, log=log,
        )  # fmt: skip
        if log is not None:
            log.info("fuse: round %d of %d: %s", r + 1, rounds + 1, result.summary.headline())
        # the cut projects the bodies with the cameras they were fitted in; its crops keep the
        # calibration's, so every fusion corrects (and reports) the rig from the calibration
        target = crops_out if last else work / f"crops_{r + 1}.h5"
        report = recut_crops(
            crops_h5, rig, videos, result.bodies, target, plates=plates, fitted_rig=result.rig,
            options=crop_options, truth_dir=truth_dir if last else None, progress=progress,
        )  # fmt: skip
        store = target
    write_body_crop_report(report, crops_out, crops_report_dir)
    shutil.rmtree(work, ignore_errors=True)
    return FuseRounds(result, report)
