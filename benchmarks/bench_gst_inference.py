"""GST inference speed per preset: pose-only versus full Gaussian output, on this machine.

Prints, per preset, the median time per batch and frames/s for the pose-only path (the
Gaussian tokens are skipped exactly) and for full output (network + posing of the Gaussians),
and the ratio between them, all in one run. Weights are random (speed does not depend on them);
the body model is the open default.

    python benchmarks/bench_gst_inference.py [--presets tiny small base] [--batch 8] [--repeats 5]
        [--device cpu|cuda|auto] [--amp]     # --amp: bf16 autocast (CUDA)
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.device import module_on, resolve_device  # noqa: E402
from gst.eval.bench import time_inference  # noqa: E402
from gst.model.assemble import assemble  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.train.recipe import build_network  # noqa: E402


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--presets", nargs="+", default=["tiny", "small", "base"])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--amp", action="store_true")
    args = ap.parse_args()
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    cpu_body = load_body_model("anny")  # networks are built on the CPU, then moved
    body = module_on(cpu_body, device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(
        f"device {name}, threads {torch.get_num_threads()}, batch {args.batch}, "
        f"{'bf16 autocast, ' if args.amp else ''}median of {args.repeats}"
    )
    print(
        f"{'preset':<7} {'input':>8} {'gaussians':>9} {'pose ms':>9} {'pose fps':>9} "
        f"{'full ms':>9} {'full fps':>9} {'full/pose':>9}"
    )
    for name in args.presets:
        cfg = get_preset(name)
        net, ids, _ = build_network(cfg, cpu_body)
        net.to(device).eval()
        vid = torch.as_tensor(ids, device=device)
        x = torch.randn(args.batch, 3, *cfg.image_size, device=device)
        K = torch.tensor([[500.0, 0, 128], [0, 500.0, 128], [0, 0, 1]], device=device)
        K = K.expand(args.batch, 3, 3)

        def run(with_gaussians: bool, net=net, x=x, K=K, vid=vid):
            with torch.no_grad(), torch.autocast(device.type, torch.bfloat16, enabled=args.amp):
                out = net(x, with_gaussians=with_gaussians)
                assemble(out, body, K, 256, vertex_ids=vid)
            if device.type == "cuda":
                torch.cuda.synchronize(device)

        t_pose = time_inference(lambda: run(False), args.repeats)
        t_full = time_inference(lambda: run(True), args.repeats)
        print(
            f"{name:<7} {cfg.image_size[0]}x{cfg.image_size[1]:<4} {len(ids):>9} "
            f"{1000 * t_pose:>9.1f} {args.batch / t_pose:>9.1f} {1000 * t_full:>9.1f} "
            f"{args.batch / t_full:>9.1f} {t_full / t_pose:>9.2f}"
        )


if __name__ == "__main__":
    main()
