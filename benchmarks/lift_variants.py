"""What the render-free pretraining samples, against single-image error (docs/landmark_prior.md,
"Pose mix and flips").

Each variant trains a fresh tiny network's landmark path (33 landmarks, lift tokens only) from
the same seed on simulated detections, then scores it on rendered worlds with BlazePose's real
detections (`gst.lift.dataset` worlds, `NAME=world.npz`), printing wall time and samples per
second beside MPJPE / PA-MPJPE and the 2D agreement of the projected limb joints with the
detected limb landmarks (% of the crop, `gst.lift.pretrain.limb_agreement`). Each variant's
sampler is the pipeline's pretraining recipe (`LiftPretrainConfig().sampler(body, "all")`) with
the variant's keys changed; every key it does not set keeps the recipe's value (not
`LiftSampler`'s own defaults, which differ: no lean, full detection noise, no limb mixing), and
the resolved settings are printed per variant. Variants are named `key=value,...` over the
recipe's sampler keys `random_share`, `uniform_p`, `whole_body_flips`, `lean_deg` (deg),
`noise_scale`, `arm_mix_p`, `leg_mix_p` (limb mixing) and the run's `steps`, `lr`, `refine`
(rounds of reprojection feedback, gst.model.refine):

    python benchmarks/lift_variants.py --steps 1500 \\
        --val demo=/work/data/lift/demo_crops.npz \\
        --val heldout=/work/data/lift/heldout/world_7000.npz \\
        --variant "random_share=0.3333,uniform_p=0.1,whole_body_flips=1" \\
        --variant "random_share=0.15,uniform_p=0.03,whole_body_flips=0"

The training loop runs on `--threads` torch threads (default: the pipeline's rule, the cores the
background sampler thread leaves).

One variant runs after another in this process (compare rows of one run only; the machine is
shared).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from gst.body import load_body_model  # noqa: E402
from gst.lift.dataset import named_worlds  # noqa: E402
from gst.lift.pretrain import LiftPretrainConfig, evaluate_world, pretrain_landmark_path  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.model.refine import DEFAULT_ROUNDS  # noqa: E402
from gst.train.recipe import build_network  # noqa: E402

# the recipe's sampler keys (LiftPretrainConfig fields that LiftPretrainConfig.sampler passes on)
SAMPLER_KEYS = {
    "random_share": float,
    "uniform_p": float,
    "whole_body_flips": lambda v: v != "0",
    "lean_deg": float,
    "noise_scale": float,
    "arm_mix_p": float,
    "leg_mix_p": float,
}
RUN_KEYS = {"steps": int, "lr": float, "refine": int}


def parse_variant(text: str) -> tuple[dict, dict]:
    """'key=value,...' -> (sampler arguments, run arguments)."""
    sampler, run = {}, {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        key = key.strip()
        if key in SAMPLER_KEYS:
            sampler[key] = SAMPLER_KEYS[key](value.strip())
        elif key in RUN_KEYS:
            run[key] = RUN_KEYS[key](value.strip())
        else:
            raise SystemExit(
                f"unknown variant key {key!r} in {text!r}; keys: {sorted(SAMPLER_KEYS | RUN_KEYS)}"
            )
    return sampler, run


def sampler_config(sampler_args: dict, seed: int) -> LiftPretrainConfig:
    """The recipe (`LiftPretrainConfig()`) with a variant's sampler keys and the run's seed."""
    return dataclasses.replace(LiftPretrainConfig(), seed=seed, **sampler_args)


def sampler_settings(cfg: LiftPretrainConfig) -> str:
    """'key=value ...' of every sampler key as `cfg` resolves it."""
    return " ".join(f"{k}={getattr(cfg, k):g}" for k in SAMPLER_KEYS)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--variant", action="append", required=True, help="key=value,... (repeat)")
    ap.add_argument("--val", action="append", required=True, help="NAME=world.npz (repeat)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads of the training loop (default: the cores the sampler thread leaves)",
    )
    args = ap.parse_args(argv)
    variants = [(text, *parse_variant(text)) for text in args.variant]  # key errors before work
    worlds = named_worlds(args.val)
    body = load_body_model("anny")
    for text, sampler_args, run_args in variants:
        torch.manual_seed(args.seed)
        cfg_net = get_preset(
            "tiny",
            landmark_tokens=True,
            num_landmarks=33,
            landmark_point_tokens=False,
            landmark_refine=run_args.get("refine", DEFAULT_ROUNDS),
        )
        net, _, _ = build_network(cfg_net, body, args.seed)
        recipe = sampler_config(sampler_args, args.seed)
        sampler = recipe.sampler(body, "all")
        cfg = dataclasses.replace(
            recipe,
            steps=run_args.get("steps", args.steps),
            batch_size=args.batch_size,
            lr=run_args.get("lr", recipe.lr),
            threads=args.threads,
        )
        print(f"{text}: sampler {sampler_settings(cfg)}", flush=True)
        t0 = time.perf_counter()
        res = pretrain_landmark_path(net, body, cfg, sampler=sampler, log=lambda *_: None)
        wall = time.perf_counter() - t0
        scores = [
            f"{name} {s.mpjpe_mm:.1f} / {s.pa_mpjpe_mm:.1f} (2D {s.limb_landmarks_pct:.2f} %)"
            for name, s in ((n, evaluate_world(net, body, w)) for n, w in worlds.items())
        ]
        print(
            f"{text}: {cfg.steps} steps in {wall:.0f} s ({res.samples_per_s:.0f} samples/s), "
            f"training batches {res.train_mpjpe_mm:.0f} mm; MPJPE / PA-MPJPE mm: "
            + "; ".join(scores),
            flush=True,
        )


if __name__ == "__main__":
    main()
