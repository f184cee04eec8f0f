"""Render-free pretraining speed, and single-image pose of checkpoints on a world they never saw.

Speed (default): the sampler alone (batches of 64 and 256) and full training steps (sample,
landmark-only forward, joints, loss, backward, AdamW) of the tiny preset's landmark path,
medians of repeated runs. The sampler is the pretraining recipe's (`LiftPretrainConfig.sampler`:
its lean, noise scale and limb mixing). Everything runs on `--threads` torch threads (default 1),
the training loop included; as in the pipeline, the training columns sample their batches
`--prefetch` steps ahead in a background thread (default the recipe's 2), which runs beside the
loop's threads; `--prefetch 0` samples in the loop, so `--threads 1 --prefetch 0` is one thread
in all. Prints one table; compare numbers taken in one run only (the machine is shared).

    python benchmarks/bench_lift.py --repeats 5

Score: each checkpoint's single-image pose (world joints, MPJPE root-aligned and PA-MPJPE,
24 joints) on the crops of a rendered world (`gst.lift.dataset` world: the scene folder and its
`world_<seed>.npz` with BlazePose's landmarks on exactly those crops), from image and landmarks
(the pipeline's path), and from the landmarks alone; with the network's time per crop. A crop
whose error is not finite is left out of the means, and the row says how many were.

    python benchmarks/bench_lift.py --score models/pretrain.pt other.pt \\
        --world /work/data/lift/heldout/scenes/world_7000 /work/data/lift/heldout/world_7000.npz
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from benchmarks.summary import finite_mean, left_out  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.lift.errors import LANDMARK_SETS  # noqa: E402
from gst.lift.pretrain import LiftPretrainConfig, pretrain_landmark_path  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.train.recipe import build_network  # noqa: E402


def _median_rate(fn, samples: int, repeats: int) -> float:
    fn()  # warm-up
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(samples / (time.perf_counter() - t0))
    return statistics.median(rates)


def score(checkpoints: list[Path], scene: Path, npz: Path) -> None:
    """Print one row per checkpoint (module doc)."""
    from gst.eval.evaluator import evaluate_pose
    from gst.lift.dataset import LandmarkWorld
    from gst.lift.pretrain import evaluate_world
    from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
    from gst.train.losses import LossWeights
    from gst.train.recipe import make_task
    from gst.train.synthetic_crops import crops_from_synth_scene

    world = LandmarkWorld.load(npz)
    crops = crops_from_synth_scene(scene, crop_size=world.crop_size)
    same = len(crops) == len(world) and np.array_equal(crops.frame.numpy(), world.frame)
    if not same or not np.allclose(crops.K.numpy(), world.K_crop, atol=1e-3):
        raise SystemExit(f"{npz} does not hold the crops of {scene} (regenerate it)")
    lm = world.landmarks.copy()
    lm[..., 2] *= world.presence[:, None]
    crops.landmarks = torch.from_numpy(lm)
    print(f"world {world.seed} ({world.rig_kind}, {len(world)} crops)")
    # ms/crop: the whole pose evaluation (network, body model, metrics) per crop, after one
    # untimed call on a few crops (the first checkpoint paid torch's first-call costs)
    print(
        "| checkpoint | image + landmarks MPJPE / PA (mm) | landmarks only | ms/crop (evaluation) |"
    )
    print("|---|---|---|---|")
    rows = torch.arange(len(crops))
    for path in checkpoints:
        ck = load_checkpoint(path)
        net = network_from_checkpoint(ck, path).eval()
        body = load_body_model(ck.body_model)
        task = make_task(body, ck.vertex_ids, net.cfg, crops.crop_size, LossWeights(lpips=0.0))
        evaluate_pose(net, task, crops, rows[:4])
        t0 = time.perf_counter()
        rec = evaluate_pose(net, task, crops, rows)
        ms = 1000 * (time.perf_counter() - t0) / len(rows)
        only = "n/a"
        if net.landmark_encoder is not None:
            s = evaluate_world(net, body, world)
            only = f"{s.mpjpe_mm:.1f} / {s.pa_mpjpe_mm:.1f}"
        # one crop with a non-finite error would make the mean NaN: left out, and counted
        ok = np.isfinite(rec.mpjpe) & np.isfinite(rec.pa_mpjpe)
        mp, dropped = finite_mean(np.where(ok, rec.mpjpe, np.nan))
        pa, _ = finite_mean(np.where(ok, rec.pa_mpjpe, np.nan))
        print(
            f"| {path} | {1000 * mp:.1f} / {1000 * pa:.1f}"
            f"{left_out(dropped, len(ok), 'crops not finite')} | {only} | {ms:.1f} |",
            flush=True,
        )


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch threads, the training loop's too")
    ap.add_argument(
        "--prefetch",
        type=int,
        default=LiftPretrainConfig.prefetch,
        help="training batches sampled ahead in a background thread (0: in the loop)",
    )
    ap.add_argument("--train-steps", type=int, default=20)
    ap.add_argument("--score", nargs="+", type=Path, help="checkpoints to score (module doc)")
    ap.add_argument("--world", nargs=2, type=Path, metavar=("SCENE", "NPZ"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.score:
        if not args.world:
            raise SystemExit("--score needs --world SCENE NPZ")
        score(args.score, *args.world)
        return
    body = load_body_model("anny")
    print("| set | sampler B=64 (samples/s) | sampler B=256 | training B=64 | training B=256 |")
    print("|---|---|---|---|---|")
    variants = (("limbs", True, 0), ("all", True, 0), ("all", False, 0), ("all", False, 2))
    for name, points, refine in variants:
        lset = LANDMARK_SETS[name]
        sampler = LiftPretrainConfig(seed=1).sampler(body, name)
        s64 = _median_rate(lambda s=sampler: s.sample(64), 64, args.repeats)
        s256 = _median_rate(lambda s=sampler: s.sample(256), 256, args.repeats)
        net, _, _ = build_network(
            get_preset(
                "tiny",
                landmark_tokens=True,
                num_landmarks=len(lset),
                landmark_point_tokens=points,
                landmark_refine=refine,
            ),
            body,
        )
        train = []
        for bs in (64, 256):
            steps = max(2, args.train_steps * 64 // bs)
            cfg = LiftPretrainConfig(
                steps=steps,
                batch_size=bs,
                warmup_steps=1,
                threads=args.threads,
                prefetch=args.prefetch,
            )

            def rate(cfg=cfg, net=net, sampler=sampler) -> float:
                run = pretrain_landmark_path(net, body, cfg, sampler=sampler, log=lambda *_: None)
                return run.samples_per_s

            rate()  # untimed: the first run on a new network and batch size is a cold one
            # an odd count of runs, so the median is one run's rate, not a mean of two
            train.append(statistics.median(rate() for _ in range(max(3, args.repeats // 2 | 1))))
        print(
            f"| {name} ({len(lset)}){'' if points else ', lift tokens only'}"
            f"{f', {refine} rounds of reprojection feedback' if refine else ''} | {s64:.0f} "
            f"| {s256:.0f} | {train[0]:.0f} | {train[1]:.0f} |"
        )


if __name__ == "__main__":
    main()
