"""What the triangulation's votes, the fit's silhouette term and the second look at crowded crops
do, per scene, on one extraction.

    python benchmarks/bench_fuse_votes.py WS/demo WS/t5000 WS/crowd_dome_7000 [--variants ...]
    python benchmarks/bench_fuse_votes.py WS/lab --fps 60 --refine-rig 2

Each workspace must hold `calibration/rig.json` and `crops/crops.h5` (after `run extract`);
`synth/` with truth makes it a synthetic scene. Every variant runs `gst.fuse.fuse_scene` on the
same crops and landmarks, into a temporary folder (no overlays), and prints, beside its run time
(the median of `--repeats` runs, default 3, taken round-robin over the variants after one untimed
run of the first variant on each scene, so first-call costs and other processes' load fall on no
variant alone; the scores are the last run's): on synthetic scenes the fused MPJPE / PA-MPJPE
(mm, against the truth), on real ones the median reprojection (full-image px) and each person's
largest per-frame limb CV. Variants (docs/fuse.md "Silhouettes"):

- `before`: leave-one-out triangulation only (the default until 2026-11-27);
- `pairs`: the pair consensus over the 8 most confident views, landmarks only;
- `silhouettes`: + the people's coverage of every view voting;
- `no_relook`: + the temporal votes (the fuse stage's defaults until crowded crops were read
  again, docs/fuse.md "Crowded crops");
- `default`: + crowded crops read again with the other people painted over, the fitted body
  judging between the two readings of each (the fuse stage's defaults);
- `relook_blind`: the second readings taken without the body's judgement;
- `relook_unpainted`: crowded crops read again as they are (the painting's ablation);
- `fit_term`: the default + the silhouette term in the body fit (weight 1).

Tune on the tuning worlds (benchmarks/tuning_scenes.yaml) and report on the others.
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from benchmarks.timing import round_robin_medians  # noqa: E402
from calibration.formats import read_rig  # noqa: E402
from gst.fuse import FitOptions, FuseOptions, TriangulationOptions, fuse_scene  # noqa: E402
from gst.fuse.relook import RelookOptions  # noqa: E402

DEFAULT = FuseOptions()
PREVIOUS = replace(DEFAULT, relook=None)
VARIANTS = {
    "before": replace(PREVIOUS, triangulation=TriangulationOptions(), silhouettes=False),
    "pairs": replace(
        PREVIOUS, triangulation=TriangulationOptions(consensus_views=8), silhouettes=False
    ),
    "silhouettes": replace(PREVIOUS, triangulation=TriangulationOptions(consensus_views=8)),
    "no_relook": PREVIOUS,
    "default": DEFAULT,
    "relook_blind": replace(DEFAULT, relook=RelookOptions(judge=False)),
    "relook_unpainted": replace(DEFAULT, relook=RelookOptions(paint=False)),
    "fit_term": replace(DEFAULT, fit=FitOptions(w_silhouette=1.0)),
}


def _videos(ws: Path) -> dict[str, Path] | None:
    folder = ws / "synth" / "videos"
    return {v.stem: v for v in sorted(folder.glob("*.mp4"))} if folder.is_dir() else None


def _percent(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.1f}"


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("workspaces", type=Path, nargs="+", help="scene workspaces (WS/<scene>)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--fps", type=float, default=None, help="frame rate when no video says it")
    ap.add_argument("--refine-rig", type=int, default=0, help="camera correction rounds")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each variant (median)")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    print(f"{'scene':<18} {'variant':<12} {'s':>6}  result (s: median of {args.repeats})")
    for ws in args.workspaces:
        rig = read_rig(ws / "calibration" / "rig.json")
        truth = ws / "synth" if (ws / "synth" / "truth").is_dir() else None

        def run(options, ws=ws, rig=rig, truth=truth):
            with tempfile.TemporaryDirectory() as tmp:
                return fuse_scene(
                    ws / "crops" / "crops.h5", rig, Path(tmp) / "fused", Path(tmp) / "report",
                    fps=args.fps, options=options, videos=_videos(ws), truth_dir=truth,
                )  # fmt: skip

        calls = [
            lambda name=name: run(
                replace(VARIANTS[name], overlay=False, refine_rig_rounds=args.refine_rig)
            )
            for name in args.variants
        ]
        for name, (seconds, result) in zip(
            args.variants, round_robin_medians(calls, args.repeats, warmup=1), strict=True
        ):
            s = result.summary
            if s.truth:
                text = (
                    f"MPJPE {s.truth['mpjpe_mm']:.1f} mm, PA-MPJPE {s.truth['pa_mpjpe_mm']:.1f} mm"
                )
            else:
                cv = ", ".join(
                    f"{p['person_id']}: {_percent(p['max_per_frame_fit_cv'])}" for p in s.people
                )
                text = f"reprojection {s.median_reprojection_px:.2f} px; limb CV % {cv}"
            print(f"{ws.name:<18} {name:<12} {seconds:6.1f}  {text}", flush=True)


if __name__ == "__main__":
    main()
