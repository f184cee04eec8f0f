"""Render-free pretraining speed: sampler samples/s and training samples/s, per landmark set.

Times the sampler alone (batches of 64 and 256) and full training steps (sample, landmark-only
forward, joints, loss, backward, AdamW) of the tiny preset's landmark path, medians of repeated
runs, 1 torch thread unless --threads. Prints one table; compare numbers taken in one run only
(the machine is shared).

    python benchmarks/bench_lift.py --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from gst.body import load_body_model
from gst.lift.errors import LANDMARK_SETS
from gst.lift.pretrain import LiftPretrainConfig, pretrain_landmark_path
from gst.lift.sampler import LiftSampler
from gst.model.presets import get_preset
from gst.train.recipe import build_network


def _median_rate(fn, samples: int, repeats: int) -> float:
    fn()  # warm-up
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(samples / (time.perf_counter() - t0))
    return statistics.median(rates)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--train-steps", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    body = load_body_model("anny")
    print("| set | sampler B=64 (samples/s) | sampler B=256 | training B=64 | training B=256 |")
    print("|---|---|---|---|---|")
    for name, points in (("limbs", True), ("all", True), ("all", False)):
        lset = LANDMARK_SETS[name]
        sampler = LiftSampler(body, landmark_set=name, seed=1)
        s64 = _median_rate(lambda s=sampler: s.sample(64), 64, args.repeats)
        s256 = _median_rate(lambda s=sampler: s.sample(256), 256, args.repeats)
        net, _, _ = build_network(
            get_preset(
                "tiny",
                landmark_tokens=True,
                num_landmarks=len(lset),
                landmark_point_tokens=points,
            ),
            body,
        )
        train = []
        for bs in (64, 256):
            steps = max(2, args.train_steps * 64 // bs)
            cfg = LiftPretrainConfig(steps=steps, batch_size=bs, warmup_steps=1)
            rates = [
                pretrain_landmark_path(
                    net, body, cfg, sampler=sampler, log=lambda *_: None
                ).samples_per_s
                for _ in range(max(1, args.repeats // 2))
            ]
            train.append(statistics.median(rates))
        print(
            f"| {name} ({len(lset)}){'' if points else ', lift tokens only'} | {s64:.0f} "
            f"| {s256:.0f} | {train[0]:.0f} | {train[1]:.0f} |"
        )


if __name__ == "__main__":
    main()
