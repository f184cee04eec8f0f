"""Speed-up of the track fan-out from 1 to 2 workers, with the local and the Ray executor.

Workload: `--videos` synthetic videos (walkers on a textured background, supplied boxes, the
pixel-free BoxDepthPredictor, so the cost is decode + crop + appearance + track + Parquet; add
the network's cost per crop on top) fanned out one item per video, and one long video split into
chunks (gst.track.chunks) fanned out one item per chunk. Every variant writes into a fresh folder
and is timed `--repeats` times; the median is printed with its speed-up over the same executor
with 1 worker. Pool start-up is inside the time for the local executor (it starts a spawn pool
per map, as the stage does); the Ray cluster is started and warmed up once per worker count,
outside the timing (its start-up is printed separately). Consistency: each output's rows must
equal a serial, unchunked, in-process run ("rows identical"), and the person count is shown.

    python benchmarks/bench_scaleout_track.py [--videos 2] [--frames 400] [--repeats 3]
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# before torch is imported (gst.track imports it): set later, the inline 1-worker variant and the
# reference ran on torch's default threads while the spawned workers had 1 each
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pyarrow.parquet as pq  # noqa: E402

from benchmarks.cli import bench_parser  # noqa: E402
from gst.track import TrackOptions  # noqa: E402
from gst.track.batch import track_videos  # noqa: E402
from gst.track.chunks import ChunkingConfig  # noqa: E402
from pipeline.executors import LocalExecutor  # noqa: E402
from tests.scaleout_scenes import job, separated_walkers  # noqa: E402
from tests.track_synthetic import render, walker_boxes, write_boxes_csv, write_video  # noqa: E402

W, H = 1280, 720


def make_clip(root: Path, name: str, frames: int) -> tuple[Path, Path]:
    walkers = separated_walkers()
    scaled = [
        type(w)(
            w.colour,
            (w.start[0] * 4, w.start[1] * 3),
            (w.velocity[0] * 0.8, w.velocity[1]),
            (w.size[0] * 3, w.size[1] * 3),
        )
        for w in walkers
    ]
    boxes = walker_boxes(scaled, frames)
    video = write_video(root / f"{name}.avi", render(scaled, boxes, W, H), W, H)
    return video, write_boxes_csv(root / f"{name}.csv", boxes, name)


def rows(path: Path):
    return pq.read_table(path).replace_schema_metadata(None)


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--videos", type=int, default=2)
    ap.add_argument(
        "--frames",
        type=int,
        default=400,
        help="frames per video (the chunked video has twice as many)",
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-ray", action="store_true")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_scaleout_"))
    options = TrackOptions(frames_per_group=25, batch_size=16)
    try:
        clips = [make_clip(tmp, f"v{i}", args.frames) for i in range(args.videos)]
        long_clip = make_clip(tmp, "long", 2 * args.frames)
        workloads = {
            f"{args.videos} videos x {args.frames} frames, 1 item per video": (
                [job(v, c, options=options) for v, c in clips],
                None,
            ),
            f"1 video x {2 * args.frames} frames, 2 chunks": (
                [job(*long_clip, options=options)],
                ChunkingConfig(chunk_frames=args.frames, overlap=10),
            ),
        }
        reference = {}
        for jobs, _ in workloads.values():
            for o in track_videos(jobs, tmp / "reference"):
                reference[o.job.name] = rows(o.result.path)

        def timed(map_fn, jobs, chunking):
            times, identical, persons = [], True, set()
            for _ in range(args.repeats):
                out = tmp / f"run-{time.perf_counter_ns()}"
                t0 = time.perf_counter()
                outcomes = track_videos(jobs, out, map_fn=map_fn, chunking=chunking)
                times.append(time.perf_counter() - t0)
                for o in outcomes:
                    identical &= rows(o.result.path).equals(reference[o.job.name])
                    persons.add(o.result.persons)
                shutil.rmtree(out)
            return statistics.median(times), identical, persons

        print(
            f"machine: {os.cpu_count()} CPU cores, shared with other users (timings are noisy); "
            f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}; {W}x{H} MJPG, BoxDepthPredictor; "
            f"median of {args.repeats}"
        )
        print(
            f"{'workload':<42} {'executor':<8} {'workers':>7} {'median s':>9} {'speed-up':>9}  "
            "consistency"
        )
        executors = [("local", lambda n: LocalExecutor(n), None)]
        if not args.no_ray:
            try:
                from pipeline.ray_executor import RayExecutor

                executors.append(("ray", lambda n: RayExecutor(n), RayExecutor))
            except ImportError as exc:
                print(f"(ray skipped: {exc})")
        for kind, factory, _ in executors:
            results: dict[tuple[str, int], float] = {}
            for n in (1, 2):
                ex = factory(n)
                if kind == "ray":
                    t0 = time.perf_counter()
                    ex.map(len, [[0]] * n, "warm-up")  # start the cluster and its workers
                    started = time.perf_counter() - t0
                    warm = [job(*make_clip(tmp, f"warm{i}", 5), options=options) for i in range(n)]
                    track_videos(warm, tmp / "warm", map_fn=ex.map)  # workers import gst once
                    print(
                        f"(ray cluster with {n} worker(s): started in {started:.1f} s, workers "
                        f"warmed up in {time.perf_counter() - t0 - started:.1f} s; neither is "
                        "timed below)"
                    )
                for name, (jobs, chunking) in workloads.items():
                    sec, same, persons = timed(ex.map, jobs, chunking)
                    results[(name, n)] = sec
                    ratio = results[(name, 1)] / sec
                    print(
                        f"{name:<42} {kind:<8} {n:>7} {sec:>9.2f} {ratio:>8.2f}x  rows identical: "
                        f"{same}, persons {sorted(persons)}"
                    )
                if kind == "ray":
                    ex.shutdown()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
