"""GST multi-view training step per preset, device and rasteriser: time against loss, one run.

One step is what `train` does per batch: draw a multi-view batch (on the CPU, as the trainer
does), move it to the device, run the network on the input crops, render the predicted
Gaussians into `--targets` other views at `--render` px with the rasteriser, the image terms
(MSE, LPIPS, alpha), backward, AdamW. Crops come from a small rendered synthetic scene (one
person, 4 dome cameras; exact truth not used). Weights are random: speed does not depend on
them; the loss after the timed steps is printed beside the time so that a fast variant that
computes something else shows up.

Variants (every combination that the machine can run, in one run): `--devices cpu cuda`,
`--backends torch gsplat` (gsplat on CUDA only, when installed), `--amp` off / bf16 autocast on
CUDA. Prints the median seconds per step over `--repeats` steps after `--warmup`, samples/s, the
peak GPU memory and, per preset, each variant's speed-up against the first row of that preset.

    python benchmarks/bench_train_step.py                         # tiny on the CPU
    python benchmarks/bench_train_step.py --devices cuda --presets tiny small base huge \\
        --backends torch gsplat --amp both --batch 16
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_overfit import one_person_scene  # noqa: E402
from benchmarks.cli import bench_parser  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.device import move_to, resolve_device  # noqa: E402
from gst.metrics.lpips import load_lpips  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.render.rasterize import _gsplat_available  # noqa: E402
from gst.train.losses import LossWeights  # noqa: E402
from gst.train.recipe import build_network, make_task  # noqa: E402
from gst.train.steps import multiview_step  # noqa: E402
from gst.train.synthetic_crops import crops_from_synth_scene  # noqa: E402
from gst.train.views import sample_multiview  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_steps(preset, device, backend, amp, crops, body, lpips, args) -> dict:
    """Median step seconds, final loss and peak memory of one variant (fresh network, seed 0)."""
    os.environ["GST_RENDER_BACKEND"] = backend
    cfg = get_preset(preset)
    net, ids, _ = build_network(cfg, body, seed=0)
    net.to(device).train()
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(), lpips).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    groups = crops.groups(min_views=2)
    gen = torch.Generator().manual_seed(0)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times, loss = [], float("nan")
    for step in range(args.warmup + args.repeats):
        _sync(device)
        t0 = time.perf_counter()
        batch = sample_multiview(crops, groups, gen, args.batch, args.targets, args.render)
        batch = move_to(batch, device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            total, _ = multiview_step(net, batch, task)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        _sync(device)
        if step >= args.warmup:
            times.append(time.perf_counter() - t0)
        loss = float(total.detach())
    peak = float("nan")
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**30
    del net, opt, task
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return {"s": statistics.median(times), "loss": loss, "peak_gib": peak}


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--presets", nargs="+", default=["tiny"])
    ap.add_argument("--devices", nargs="+", default=["cpu"])
    ap.add_argument("--backends", nargs="+", default=["torch", "gsplat"])
    ap.add_argument("--amp", choices=["off", "on", "both"], default="off")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--render", type=int, default=64)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument(
        "--scene", type=Path, default=None, help="a rendered synthetic scene folder to cut the "
        "crops from (default: render the one-person scene into a temporary folder)",
    )  # fmt: skip
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.scene is not None:
        crops = crops_from_synth_scene(args.scene, crop_size=128)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            crops = one_person_scene(tmp, cameras=4)
    body, lpips = load_body_model("anny"), load_lpips()
    devices = [resolve_device(d) for d in args.devices]
    print(
        f"batch {args.batch}, {args.targets} target views at {args.render} px, crops "
        f"{crops.crop_size} px, median of {args.repeats} steps after {args.warmup}; CPU threads "
        f"{torch.get_num_threads()}; "
        + ", ".join(f"{d}: {torch.cuda.get_device_name(d)}" for d in devices if d.type == "cuda")
    )
    print(
        f"{'preset':<6} {'device':<6} {'raster':<7} {'amp':<4} {'s/step':>8} {'samples/s':>9} "
        f"{'loss':>7} {'peak GiB':>8} {'speed-up':>8}"
    )
    amps = {"off": [False], "on": [True], "both": [False, True]}[args.amp]
    not_run = set()  # requested variants this machine cannot run, said once at the end
    for preset in args.presets:
        first = None
        for device in devices:
            for backend in args.backends:
                if backend == "gsplat" and (device.type != "cuda" or not _gsplat_available()):
                    why = "CUDA only" if device.type != "cuda" else "not installed"
                    not_run.add(f"{device.type} gsplat ({why})")
                    continue
                for amp in amps:
                    if amp and device.type != "cuda":
                        not_run.add(f"{device.type} bf16 autocast (CUDA only)")
                        continue
                    try:
                        r = time_steps(preset, device, backend, amp, crops, body, lpips, args)
                    except torch.OutOfMemoryError:
                        print(f"{preset:<6} {device.type:<6} {backend:<7} {amp!s:<4} out of memory")
                        torch.cuda.empty_cache()
                        continue
                    first = first or r["s"]
                    peak = "-" if math.isnan(r["peak_gib"]) else f"{r['peak_gib']:.2f}"  # CPU: none
                    print(
                        f"{preset:<6} {device.type:<6} {backend:<7} {'bf16' if amp else '-':<4} "
                        f"{r['s']:>8.3f} {args.batch / r['s']:>9.1f} {r['loss']:>7.3f} "
                        f"{peak:>8} {first / r['s']:>7.2f}x",
                        flush=True,
                    )
    if not_run:
        print("not run: " + ", ".join(sorted(not_run)))
    os.environ.pop("GST_RENDER_BACKEND", None)


if __name__ == "__main__":
    main()
