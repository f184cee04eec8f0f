"""The extraction's crops against the crops cut again from the fitted bodies, on synthetic
scenes with truth, in one run.

    python benchmarks/bench_bodycrops.py workspace/crowd_dome_7000 workspace/crowd_h36m_7000 ...
    python benchmarks/bench_bodycrops.py workspace/crowd_h36m_7000 --max-distance 2 8 1e9

Each workspace must hold `calibration/rig.json`, `crops/crops.h5` (`run extract`),
`fused/bodies.parquet` (`run fuse`) and `synth/` (a rendered scene with its board clips and
truth). Per scene it prints the extraction's mask IoU, association accuracy and missed truth
views (those at least 30 % visible, as the extraction's report counts them), then the same for
`gst.fuse.body_crops.recut_crops` with each `--max-distance` (pixels at the working size) and
its run time; last, the means over the scenes. The new stores go to a temporary folder.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from calibration.formats import read_rig  # noqa: E402
from gst.data.store import CropStore  # noqa: E402
from gst.fuse.body_crops import BodyCropOptions, recut_crops  # noqa: E402


def _extraction(ws: Path) -> tuple[float, float, int, int]:
    import json

    report = json.loads((ws / "reports" / "extract" / "extract.json").read_text())
    return (
        report["mask_iou"], report["association_accuracy"], report["visible_views_missed"],
        report["visible_views"],
    )  # fmt: skip


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("workspaces", type=Path, nargs="+", help="scene workspaces (WS/<scene>)")
    ap.add_argument("--max-distance", type=float, nargs="+", default=[8.0])
    args = ap.parse_args()
    head = f"{'scene':18s} {'variant':24s} {'s':>6s} {'crops':>6s} {'IoU':>6s} {'assoc':>6s}"
    print(f"{head} {'missed (>=30% visible)':>24s}")
    totals: dict[str, list[tuple[float, float, float]]] = {}
    for ws in args.workspaces:
        rig = read_rig(ws / "calibration" / "rig.json")
        iou, acc, missed, views = _extraction(ws)
        n = len(CropStore(ws / "crops" / "crops.h5"))
        print(
            f"{ws.name:18s} {'extraction':24s} {'':>6s} {n:6d} {iou:6.3f} {acc:6.3f} "
            f"{missed:9d} of {views:5d} ({missed / max(views, 1):.3f})"
        )
        totals.setdefault("extraction", []).append((iou, acc, missed / max(views, 1)))
        for d in args.max_distance:
            name = f"bodycrops, {d:g} px"
            with tempfile.TemporaryDirectory() as tmp:
                rep = recut_crops(
                    ws / "crops" / "crops.h5", rig,
                    {c.name: ws / "synth" / "videos" / f"{c.name}.mp4" for c in rig},
                    ws / "fused" / "bodies.parquet", Path(tmp) / "crops.h5",
                    plates={c.name: ws / "synth" / "board" / f"{c.name}.mp4" for c in rig},
                    options=BodyCropOptions(max_distance_px=d), truth_dir=ws / "synth",
                )  # fmt: skip
            share = rep.visible_views_missed / max(rep.visible_views, 1)
            print(
                f"{ws.name:18s} {name:24s} {rep.seconds:6.1f} {rep.crops:6d} {rep.mask_iou:6.3f} "
                f"{rep.association_accuracy:6.3f} {rep.visible_views_missed:9d} of "
                f"{rep.visible_views:5d} ({share:.3f})",
                flush=True,
            )
            totals.setdefault(name, []).append((rep.mask_iou, rep.association_accuracy, share))
    print("\nmeans over the scenes (missed: mean of the scenes' shares):")
    for name, rows in totals.items():
        iou, acc, share = np.mean(rows, axis=0)
        print(f"  {name:24s} IoU {iou:.3f}  association {acc:.3f}  missed {share:.3f}")


if __name__ == "__main__":
    main()
