"""Run time beside error for the metrics that sit in training and evaluation loops.

1. LPIPS as a loss (forward + backward) and as a metric (forward), alex vs vgg, float32 vs bf16
   autocast: median ms per batch, and the bf16 values' deviation from float32.
2. PA-MPJPE: batched torch (float64 SVD) vs a per-sample numpy Umeyama loop: median time and
   the largest difference between the two.

    python benchmarks/bench_metrics.py [--device cpu|cuda] [--batch 8] [--size 256]
        [--repeats 5] [--threads N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from gst.metrics.lpips import load_lpips  # noqa: E402
from gst.metrics.lpips_weights import LPIPSWeightsMissing, fetch_command  # noqa: E402
from gst.metrics.pose import pa_mpjpe  # noqa: E402


def _median_s(fn: Callable[[], object], repeats: int, device: torch.device) -> float:
    fn()  # warm-up (allocations, oneDNN / cuDNN kernel choice)
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_lpips(device: torch.device, batch: int, size: int, repeats: int) -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.rand(batch, 3, size, size, generator=g).to(device)
    y = (x + 0.1 * torch.randn(x.shape, generator=g).to(device)).clamp(0, 1)
    print(f"LPIPS, batch {batch} x 3 x {size} x {size}, {device}")
    print(
        f"{'net':5} {'precision':9} {'forward ms':>11} {'fwd+bwd ms':>11} {'max |d - d_fp32|':>17} "
        f"{'fwd+bwd vs alex fp32':>21}"
    )
    base = None
    for net in ("alex", "vgg"):
        try:
            model = load_lpips(net, device=device)
        except LPIPSWeightsMissing:  # vgg is optional: `fetch` gets alex unless told
            print(f"{net:5} not run: weights not cached ({fetch_command(net)})")
            continue
        with torch.no_grad():
            ref = model(x, y)
        for precision in ("fp32", "bf16"):

            def autocast(precision=precision):
                return torch.autocast(
                    device.type, dtype=torch.bfloat16, enabled=precision == "bf16"
                )

            def forward(model=model, autocast=autocast):
                with torch.no_grad(), autocast():
                    return model(x, y)

            def forward_backward(model=model, autocast=autocast):
                xg = x.clone().requires_grad_(True)
                with autocast():
                    d = model(xg, y)
                d.float().mean().backward()

            t_f = _median_s(forward, repeats, device)
            t_fb = _median_s(forward_backward, repeats, device)
            err = (forward().float() - ref).abs().max().item()
            base = base or t_fb
            print(
                f"{net:5} {precision:9} {t_f * 1e3:11.1f} {t_fb * 1e3:11.1f} {err:17.2e} "
                f"{t_fb / base:20.2f}x"
            )


def _umeyama_loop(p: np.ndarray, g: np.ndarray) -> np.ndarray:
    out = np.empty(len(p))
    for i in range(len(p)):
        mu_p, mu_g = p[i].mean(0), g[i].mean(0)
        pc, gc = p[i] - mu_p, g[i] - mu_g
        u, s, vt = np.linalg.svd(gc.T @ pc / len(pc))
        d = np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
        rot = (u * d) @ vt
        scale = (s * d).sum() / (pc**2).sum(1).mean()
        aligned = scale * pc @ rot.T + mu_g
        out[i] = np.linalg.norm(aligned - g[i], axis=-1).mean()
    return out


def bench_pa_mpjpe(device: torch.device, repeats: int, batch: int = 4096, joints: int = 24) -> None:
    rng = np.random.default_rng(0)
    g = rng.normal(scale=0.4, size=(batch, joints, 3))
    p = g + rng.normal(scale=0.05, size=g.shape)
    pt, gt = torch.from_numpy(p).to(device), torch.from_numpy(g).to(device)
    t_torch = _median_s(lambda: pa_mpjpe(pt, gt), repeats, device)
    t_np = _median_s(lambda: _umeyama_loop(p, g), max(1, repeats // 2), torch.device("cpu"))
    diff = np.abs(pa_mpjpe(pt, gt).cpu().numpy() - _umeyama_loop(p, g)).max()
    print(f"\nPA-MPJPE, {batch} poses x {joints} joints")
    print(f"{'variant':24} {'ms':>9} {'speed-up':>9} {'max |diff| (m)':>15}")
    print(f"{'numpy loop (reference)':24} {t_np * 1e3:9.1f} {1.0:8.1f}x {0.0:15.1e}")
    print(
        f"{'torch batched ' + device.type:24} {t_torch * 1e3:9.1f} {t_np / t_torch:8.1f}x "
        f"{diff:15.1e}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch CPU threads (0: torch's default); 1 is steadier on a shared machine",
    )
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}")
    bench_lpips(device, args.batch, args.size, args.repeats)
    bench_pa_mpjpe(device, args.repeats)


if __name__ == "__main__":
    main()
