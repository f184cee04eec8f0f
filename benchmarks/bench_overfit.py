"""Overfit one multi-view sample (the paper's capacity check, 41 dB there): PSNR against time.

Renders a one-person synthetic scene (4 cameras), cuts its crops with exact truth, and overfits
the tiny preset on one (frame, person) with `gst.train.overfit.overfit_sample`: a short
supervised warm start, then the multi-view objective alone (MSE + LPIPS + alpha + tightness).
PSNR is on the training views (every view as input in turn, all views rendered, person on
black). Variants in one run: the Gaussian head and the body on separate learning rates (the
default), one shared rate for everything, and a larger render size. Goal: >= 30 dB in < 3 min.

    python benchmarks/bench_overfit.py [--steps 600] [--threads 2]
        [--variants split shared split128]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.metrics.lpips import load_lpips  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.train.losses import LossWeights  # noqa: E402
from gst.train.overfit import overfit_sample  # noqa: E402
from gst.train.recipe import build_network, make_task  # noqa: E402
from gst.train.synthetic_crops import crops_from_synth_scene  # noqa: E402
from synth.scene import preset, render_scene  # noqa: E402

VARIANTS = {  # name: (Gaussian-head lr, body lr, render size)
    "split": (2e-3, 1e-5, 64),
    "shared": (2e-3, 2e-3, 64),
    "split128": (2e-3, 1e-5, 128),
}


def one_person_scene(out_dir: str, seed: int = 7, cameras: int = 4):
    spec = preset(
        "demo",
        seed=seed,
        n_frames=2,
        n_people=1,
        motions=[["jump"]],
        rig={"kind": "dome", "n_cameras": cameras, "width": 320, "height": 240},
        board={"n_frames": 1},
    )
    render_scene(spec, out_dir)
    return crops_from_synth_scene(out_dir, crop_size=128)


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--warm-steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--variants", nargs="+", default=["split", "shared"], choices=list(VARIANTS))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        crops = one_person_scene(tmp)
    group = crops.groups(min_views=2)[0]
    body, lpips, cfg = load_body_model("anny"), load_lpips(), get_preset("tiny")
    print(
        f"one sample, {len(group)} views, crops {crops.crop_size}px, tiny preset, "
        f"{args.warm_steps} warm-start + {args.steps} multi-view steps, torch threads "
        f"{torch.get_num_threads()}"
    )
    print(
        f"{'variant':<9} {'lr gauss':>8} {'lr body':>8} {'render':>6} {'warm mm':>7} "
        f"{'PSNR dB':>7} {'s total':>7} {'s to 30 dB':>10}"
    )
    rows = {}
    for name in args.variants:
        lr, body_lr, size = VARIANTS[name]
        net, ids, _ = build_network(cfg, body, seed=0)
        task = make_task(body, ids, cfg, crops.crop_size, LossWeights(), lpips)
        t0 = time.perf_counter()
        r = overfit_sample(
            net,
            task,
            crops,
            group,
            warm_steps=args.warm_steps,
            steps=args.steps,
            lr=lr,
            body_lr=body_lr,
            render_size=size,
            eval_every=50,
        )
        reached = next((h["seconds"] for h in r.history if h["psnr"] >= 30), None)
        rows[name] = r
        print(
            f"{name:<9} {lr:>8.0e} {body_lr:>8.0e} {size:>6} "
            f"{r.warm_mpjpe_mm or float('nan'):>7.1f} {r.psnr:>7.2f} "
            f"{time.perf_counter() - t0:>7.1f} "
            f"{'never' if reached is None else f'{reached:.1f}':>10}"
        )
        print(
            "          PSNR by step: "
            + ", ".join(f"{h['step']}:{h['psnr']:.1f}" for h in r.history)
        )
    if "split" in rows and "shared" in rows:
        print(f"split vs shared learning rates: {rows['split'].psnr - rows['shared'].psnr:+.2f} dB")


if __name__ == "__main__":
    main()
