"""The fuse stage's recipe: fuse the extraction's crops, then cut the crops again from the
fitted bodies and fuse again on those, up to `rounds` times; last, cut the crops from the final
bodies for the user and for training (docs/fuse.md "Crops from the fitted bodies").

Crops cut from the bodies carry the fused ids in every camera, a crop in every view that shows
the person (read again where others crowd it), and masks nearer the truth, so the second fusion
sees its people more completely and paints the others out more exactly: on the six crowd
scenes the fused error fell from 50.1 to 44.4 mm (docs/fuse.md). Where the cut agrees with the
extraction (`agreement`: nearly every crop of either pairs one to one with one of the other's
by mask overlap, as on the demo and the lab capture, whose people seldom hide each other), the
extraction already found each person's views with nearly the bodies' masks, and fusing again
changes little (the demo 0.8 mm worse, the lab 0.1 px better): the fusion stops there and its
cut is the last (`skip_agreement`).

Every cut takes its landmarks and extra foreground from the extraction's store, never from an
earlier cut. A resumed run starts again from the first fusion's fit (each fusion removes its
work folder when it finishes, and each cut is written anew).
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
    fusions: int  # how many fusions ran (1 + the rounds that the scene needed)


def fuse_rounds(
    crops_h5: Path,
    rig: Rig,
    out_dir: Path,
    report_dir: Path,
    crops_out: Path,
    crops_report_dir: Path,
    *,
    rounds: int = 1,
    skip_agreement: float | None = 0.98,
    fps: float | None = None,
    options: FuseOptions | None = None,
    crop_options: BodyCropOptions | None = None,
    videos: dict[str, Path],
    plates: dict[str, Path] | None = None,
    truth_dir: Path | None = None,
    progress=None,
    log=None,
    reading_cache: Path | None = None,
) -> FuseRounds:
    """Fuse `crops_h5` (the extraction's store) into `out_dir` / `report_dir` after up to
    `rounds` rounds of cutting the crops again from the bodies and fusing those; the crops cut
    from the final bodies go to `crops_out` (report in `crops_report_dir`). A cut whose
    agreement with the extraction (`BodyCropReport.agreement`) is at least `skip_agreement`
    ends the rounds (None: every round runs). `videos` and `plates` (clean plates, None: the
    background is learnt from the videos) are per camera; `reading_cache`: fuse_scene's."""
    options = options or FuseOptions()
    crop_options = crop_options or BodyCropOptions()
    work = out_dir.parent / f".{out_dir.name}.rounds"
    store = crops_h5
    quiet = dataclasses.replace(options, overlay=False)
    for r in range(rounds + 1):
        last = r == rounds
        where = (out_dir, report_dir) if last else (work / f"fused_{r}", work / f"report_{r}")
        result = fuse_scene(
            store, rig, *where, fps=fps, options=options if last else quiet,
            truth_dir=truth_dir, videos=videos, progress=progress, log=log,
            reading_cache=reading_cache,
        )  # fmt: skip
        if log is not None:
            log.info("fuse: fusion %d of at most %d: %s", r + 1, rounds + 1,
                     result.summary.headline())  # fmt: skip
        # the cut projects the bodies with the cameras they were fitted in; its crops keep the
        # calibration's, so every fusion corrects (and reports) the rig from the calibration
        target = crops_out if last else work / f"crops_{r + 1}.h5"
        report = recut_crops(
            crops_h5, rig, videos, result.bodies, target, plates=plates, fitted_rig=result.rig,
            options=crop_options, truth_dir=truth_dir, progress=progress,
        )  # fmt: skip
        if log is not None:
            log.info("fuse: cut %d: %s", r + 1, report.summary_line())
        if not last and skip_agreement is not None and report.agreement() >= skip_agreement:
            if log is not None:
                log.info(
                    "fuse: the bodies' crops agree with the extraction's (%.3f >= %.3f): no "
                    "further fusion (fuse.recut_agreement)", report.agreement(), skip_agreement,
                )  # fmt: skip
            result = _promote(result, where, out_dir, report_dir, options, videos, progress)
            _replace(target, crops_out)
            break
        store = target
    write_body_crop_report(report, crops_out, crops_report_dir)
    shutil.rmtree(work, ignore_errors=True)
    return FuseRounds(result, report, r + 1)


def _promote(result: FuseResult, where, out_dir: Path, report_dir: Path,
             options: FuseOptions, videos, progress) -> FuseResult:  # fmt: skip
    """An intermediate fusion made the final one: its outputs moved to the stage's folders, and
    the overlays (not drawn for an intermediate fusion) drawn."""
    for src, dst in zip(where, (out_dir, report_dir), strict=True):
        if dst.exists():
            shutil.rmtree(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(src), str(dst))

    def moved(p: Path) -> Path:
        return out_dir / p.relative_to(where[0])

    overlays: list[Path] = []
    if options.overlay and result.fits:
        from gst.body import load_body_model
        from gst.fuse.overlay import write_overlays

        body = load_body_model(options.body_model)
        shown = {k: Path(v) for k, v in videos.items() if Path(v).is_file()}
        overlays = write_overlays(
            result.fits, body, result.rig, shown, report_dir / "overlay", progress=progress
        )
    return dataclasses.replace(
        result, bodies=moved(result.bodies), landmarks=moved(result.landmarks),
        trc=[moved(p) for p in result.trc], c3d=[moved(p) for p in result.c3d], overlays=overlays,
    )  # fmt: skip


def _replace(store: Path, to: Path) -> None:
    """A crop store (and its Parquet index) moved to `to`, replacing what is there."""
    import pyarrow.parquet as pq

    from gst.atomic import atomic_path
    from gst.data.store import index_path_for

    to.parent.mkdir(parents=True, exist_ok=True)
    # the index names its store: the same rows, under the new name
    table = pq.read_table(index_path_for(store))
    meta = {**(table.schema.metadata or {}), b"store": to.name.encode()}
    with atomic_path(index_path_for(to)) as tmp:
        pq.write_table(table.replace_schema_metadata(meta), tmp)
    store.replace(to)
    index_path_for(store).unlink()
