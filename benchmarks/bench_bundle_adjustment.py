"""Bundle adjustment speed and accuracy: 8 cameras x 100 board views (issue 3; goal < 10 s).

Synthetic detections with known truth (0.3 px corner noise, a ring of 8 cameras, no board
pose seen by all). The initial solution (intrinsics, pose graph) is computed once; every BA
variant then starts from the same state. Each variant runs `--repeats` times; the table shows
the median wall time, its ratio to the first variant run (the default unless `--only` leaves
it out), and the accuracy of the calibrated rig against
the truth: worst focal error (%), worst centre error (% of rig diameter), worst rotation
error (degrees) and the final RMS (px).

    python benchmarks/bench_bundle_adjustment.py [--frames 100] [--repeats 3] [--outliers 0.02]
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from calibration.board import FrameDetection  # noqa: E402
from calibration.bundle import BAOptions  # noqa: E402
from calibration.posegraph import invert, rotation_angle_deg  # noqa: E402
from calibration.solve import (  # noqa: E402
    SolveOptions,
    bundle_adjust,
    finish_calibration,
    initialise_from_detections,
)
from calibration.synthetic import FLOOR_BOARD_AXES, make_scene, synthetic_detections  # noqa: E402

VARIANTS = {
    "default (cauchy 1px, auto solver)": BAOptions(),
    "loss trivial": BAOptions(loss="trivial"),
    "loss huber": BAOptions(loss="huber"),
    "loss soft_l1": BAOptions(loss="soft_l1"),
    "1 thread": BAOptions(num_threads=1),
    "SPARSE_NORMAL_CHOLESKY": BAOptions(linear_solver="SPARSE_NORMAL_CHOLESKY"),
    "DENSE_SCHUR": BAOptions(linear_solver="DENSE_SCHUR"),
    "SPARSE_SCHUR": BAOptions(linear_solver="SPARSE_SCHUR"),
    "ITERATIVE_SCHUR": BAOptions(linear_solver="ITERATIVE_SCHUR"),
    "no outlier rounds": BAOptions(max_outlier_rounds=0),
}


def corrupt(detections, fraction, rng):
    """Move `fraction` of all corners by 5-20 px (gross detection errors)."""
    out, n = {}, 0
    for name, dets in detections.items():
        new = []
        for d in dets:
            c = d.corners.copy()
            bad = rng.uniform(size=len(c)) < fraction
            c[bad] += rng.choice([-1, 1], (bad.sum(), 2)) * rng.uniform(5, 20, (bad.sum(), 2))
            n += int(bad.sum())
            new.append(FrameDetection(d.frame, d.ids, c))
        out[name] = new
    return out, n


def accuracy(result, scene):
    F = np.eye(4)
    F[:3, :3] = FLOOR_BOARD_AXES
    T = F @ invert(scene.world_from_board[scene.floor_frame])
    truth = scene.rig.transformed(T[:3, :3], T[:3, 3])
    c = np.array([cam.center for cam in truth])
    diameter = max(np.linalg.norm(a - b) for a in c for b in c)
    f_err = max(
        max(abs(e.fx / t.fx - 1), abs(e.fy / t.fy - 1))
        for t, e in zip(truth, result.rig, strict=True)
    )
    c_err = (
        max(np.linalg.norm(e.center - t.center) for t, e in zip(truth, result.rig, strict=True))
        / diameter
    )
    r_err = max(rotation_angle_deg(e.R, t.R) for t, e in zip(truth, result.rig, strict=True))
    return 100 * f_err, 100 * c_err, r_err, result.rms_px_overall


def main(argv=None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument(
        "--outliers", type=float, default=0.0, help="fraction of corners made gross outliers"
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default=None, help="run only variants whose name contains this")
    args = ap.parse_args(argv)

    scene = make_scene(n_cameras=args.cameras, n_frames=args.frames, seed=args.seed)
    dets = synthetic_detections(scene, noise_px=args.noise, seed=args.seed)
    n_bad = 0
    if args.outliers > 0:
        dets, n_bad = corrupt(dets, args.outliers, np.random.default_rng(args.seed + 99))
    sizes = {c.name: (c.width, c.height) for c in scene.rig}
    views = sum(len(v) for v in dets.values())
    corners = sum(len(d.ids) for v in dets.values() for d in v)
    t0 = time.perf_counter()
    init = initialise_from_detections(dets, sizes, scene.board)
    t_init = time.perf_counter() - t0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"machine: {os.cpu_count()} CPUs, load average {load:.1f} (wall times grow with load; CPU "
        "s is process CPU time, all threads)"
    )
    print(
        f"{args.cameras} cameras x {args.frames} board poses: {views} views, {corners} corners, "
        f"noise {args.noise} px, {n_bad} gross outliers"
    )
    print(
        f"initialisation (intrinsics + pose graph): {t_init:.2f} s  "
        f"({', '.join(f'{k} {v:.2f} s' for k, v in init.timings.items())})"
    )
    print()
    header = (
        f"{'variant':36s} {'BA s (median)':>13s} {'ratio':>6s} {'CPU s':>6s} {'rounds':>6s} "
        f"{'f err %':>8s} {'centre %':>8s} {'rot deg':>8s} {'RMS px':>7s} {'removed':>7s}"
    )
    print(header)
    print("-" * len(header))
    base = None
    for name, ba_opts in VARIANTS.items():
        if args.only and args.only not in name:
            continue
        opts = replace(SolveOptions(), ba=ba_opts)
        times, cpu, result = [], [], None
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            ba = bundle_adjust(init, opts)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            result = finish_calibration(init, ba)
        med = statistics.median(times)
        base = base or med
        f_err, c_err, r_err, rms = accuracy(result, scene)
        removed = sum(r["removed"] for r in result.ba_rounds)
        print(
            f"{name:36s} {med:13.2f} {med / base:6.2f} {statistics.median(cpu):6.2f} "
            f"{len(result.ba_rounds):6d} {f_err:8.3f} {c_err:8.3f} {r_err:8.3f} {rms:7.3f} "
            f"{removed:7d}"
        )
    print()
    print(
        "goal: BA under 10 s; acceptance: f err < 0.5 %, centre < 1 %, rotation < 0.3 deg, RMS < "
        "0.5 px"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
