"""Wall time of rendering a synth preset serially and fanned out over 2 local worker processes.

Variants: `serial` (no map_fn, one share per memory group), `local-2 shares=2` (LocalExecutor(2),
one share per worker, as the stage does) and `local-2 shares=N` (one camera per share: the Embree
scene and floor shadows are rebuilt for every camera and frame). The body model is loaded once
outside the timing (workers never load it; the posed cast reaches them as .npy files). The
spawn pool's start-up is inside the time, as in the stage. Each fanned-out folder must be
byte-identical to the serial one ("files identical"). Times are medians over `--repeats`; "cpu s"
is the CPU time of this process and the pool's workers together (the fan-out's overhead, which on
a machine loaded by other users shows better than the wall time).

    OMP_NUM_THREADS=1 python benchmarks/bench_scaleout_synth.py [--preset demo] [--repeats 1]
        [--body anny|capsule]
"""

from __future__ import annotations

import hashlib
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from pipeline.executors import LocalExecutor  # noqa: E402
from synth.scene import preset, render_scene  # noqa: E402


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def cpu_seconds() -> float:
    """User + system CPU time of this process and its finished child processes (the pool's)."""
    own, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument(
        "--body",
        choices=["anny", "capsule"],
        default="anny",
        help="'capsule': the test fixture's fast fake body instead of the spec's model",
    )
    args = ap.parse_args()
    spec = preset(args.preset)
    if args.body == "capsule":
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from synth_fixtures import CapsuleBody

        body = CapsuleBody()
    else:
        from gst.body import load_body_model

        body = load_body_model(spec.body_model)
    n_cams = spec.rig.n_cameras or 1
    variants = [
        ("serial", None, None),
        ("local-2 shares=2", LocalExecutor(2).map, 2),
        (f"local-2 shares={n_cams}", LocalExecutor(2).map, n_cams),
    ]
    print(
        f"preset {args.preset}: {spec.n_frames} frames + {spec.board.n_frames} board frames, "
        f"{n_cams} cameras {spec.rig.width}x{spec.rig.height}, body {args.body}; "
        f"os.cpu_count()={os.cpu_count()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        reference = None
        times = {}
        for r in range(args.repeats):
            for name, map_fn, shares in variants:
                out = Path(tmp) / f"{name.replace(' ', '_')}-{r}"
                cpu0, t0 = cpu_seconds(), time.perf_counter()
                render_scene(spec, out, body_model=body, map_fn=map_fn, shares=shares)
                times.setdefault(name, []).append(time.perf_counter() - t0)
                times.setdefault(name + ":cpu", []).append(cpu_seconds() - cpu0)
                files = digest(out)
                reference = reference or files
                times.setdefault(name + ":same", []).append(files == reference)
        base = statistics.median(times["serial"])
        print(
            f"{'variant':<18}{'median s':>10}{'speed-up':>10}{'cpu s':>8}  files identical to "
            "serial"
        )
        for name, _, _ in variants:
            t, cpu = statistics.median(times[name]), statistics.median(times[name + ":cpu"])
            print(f"{name:<18}{t:>10.1f}{base / t:>10.2f}{cpu:>8.1f}  {all(times[name + ':same'])}")


if __name__ == "__main__":
    main()
