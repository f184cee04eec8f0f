"""The GST paper's Table 1 and Table 5 on our synthetic world, in one run.

From the pretrained model (models/pretrain.pt) and the demo scene's extracted crops, every row
is fine-tuned with the same step budget on the same training split (earlier frames, training
cameras) and scored by the same evaluator on the test split (later frames; pose on every camera,
novel views rendered into the held-out camera):

  Table 1: pretrained only | 2D-only fine-tuned (2D joint labels) | 3D fine-tuned (3D labels)
           | GST multi-view (no labels; paper losses)
  Table 5: GST without the LPIPS term | without tightness | without the alpha (transparency) term

Columns: MPJPE and PA-MPJPE (mm), PSNR / SSIM / LPIPS in held-out views (full crop), the SHERF
box PSNR, and the run time of each row (training + evaluation). Prints the markdown table and
writes it to --out.

    python benchmarks/bench_paper_tables.py --workspace workspace/demo [--steps 300] [--threads 2]
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import torch

from gst.body import load_body_model
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.split import FinetuneConfig, finetune, frame_split
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.train.losses import LossWeights
from gst.train.recipe import make_task
from gst.train.scene_truth import attach_scene_truth
from gst.train.views import load_cropset

PAPER = LossWeights()  # paper weights: LPIPS 0.01, alpha 0.1, tightness 0.1
ROWS = [
    ("Table 1", "pretrained only", None, PAPER),
    ("Table 1", "2D-only fine-tuned", "2d", PAPER),
    ("Table 1", "3D fine-tuned", "3d", PAPER),
    ("Table 1", "GST multi-view", "multiview", PAPER),
    ("Table 5", "GST w/o LPIPS", "multiview", PAPER.model_copy(update={"lpips": 0.0})),
    ("Table 5", "GST w/o tightness", "multiview", PAPER.model_copy(update={"tightness": 0.0})),
    (
        "Table 5",
        "GST w/o alpha (transparency)",
        "multiview",
        PAPER.model_copy(update={"alpha": 0.0}),
    ),
]


def _f(v, d=1) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--workspace", type=Path, default=Path("workspace/demo"), help="scene workspace (synthetic)"
    )
    ap.add_argument("--steps", type=int, default=300, help="fine-tuning steps of every row")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--render-size", type=int, default=128, help="evaluation render size (px)")
    ap.add_argument("--test-fraction", type=float, default=0.25)
    ap.add_argument("--rows", nargs="*", help="row names to run (default: all)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="markdown output (default: <workspace>/reports/paper_tables.md)",
    )
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    ws = args.workspace
    crops, boxes = load_cropset(ws / "crops" / "crops.h5")
    truth = attach_scene_truth(crops, boxes, ws / "synth")
    heldout = tuple(crops.camera_names[-1:])
    split = frame_split(crops, heldout, args.test_fraction)
    ckpt = load_checkpoint(ws / "models" / "pretrain.pt")
    body = load_body_model(ckpt["body_model"])
    base = network_from_checkpoint(ckpt)
    ids, groups = ckpt["vertex_ids"].numpy(), ckpt["group_index"].numpy()
    lpips = load_lpips()
    vertices = truth.vertices(body) if ckpt["body_model"] == truth.body_model else None
    eval_cfg = EvalConfig(
        heldout_cameras=heldout,
        render_size=args.render_size,
        frames=split.test_frames,
        side_by_side_groups=0,
    )
    print(
        f"preset {base.cfg.name}, {torch.get_num_threads()} threads; {args.steps} steps x batch {args.batch} per row "
        f"(lr {args.lr}); train: {len(split.train_rows)} crops of frames < {split.test_frames[0]} outside {heldout}; "
        f"test: frames {split.test_frames[0]}-{split.test_frames[1] - 1}; novel views at {args.render_size} px",
        flush=True,
    )
    results = []
    t_all = time.perf_counter()
    for table, name, mode, weights in ROWS:
        if args.rows and name not in args.rows:
            continue
        t0 = time.perf_counter()
        net = copy.deepcopy(base)
        train_s = 0.0
        if mode is not None:
            cfg = FinetuneConfig(
                mode=mode, steps=args.steps, batch_size=args.batch, lr=args.lr, weights=weights
            )
            train_s = finetune(
                net, body, ids, groups, crops, split, cfg, body_spec=ckpt["body_model"], lpips=lpips
            )
        task = make_task(body, ids, net.cfg, crops.crop_size, LossWeights(lpips=0.0))
        res = evaluate_model(
            net,
            task,
            crops,
            eval_cfg,
            joint_names=truth.joint_names,
            lpips=lpips,
            scene_vertices=vertices,
            motions=truth.motion,
        )
        p, v = res.summary["pose"]["overall"], res.summary["novel_view"]["heldout"]
        results.append((table, name, p, v, train_s, time.perf_counter() - t0))
        print(
            f"{table} {name}: MPJPE {_f(p['mpjpe_mm'])} PA-MPJPE {_f(p['pa_mpjpe_mm'])} PSNR {_f(v['psnr'], 2)} "
            f"SSIM {_f(v['ssim'], 3)} LPIPS {_f(v['lpips'], 3)} ({train_s:.0f} s training, "
            f"{time.perf_counter() - t0:.0f} s total)",
            flush=True,
        )
    lines = [
        f"Fine-tuning budget per row: {args.steps} steps x batch {args.batch}; total {time.perf_counter() - t_all:.0f} s "
        f"on CPU ({torch.get_num_threads()} threads). Pose on {res.summary['counts']['pose_crops']} test crops; "
        f"novel views: {v['n']} held-out-camera pairs.",
        "",
        "| table | row | MPJPE (mm) | PA-MPJPE (mm) | PSNR (dB) | SSIM | LPIPS | box PSNR (dB) | train s | total s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for table, name, p, v, train_s, total in results:
        lines.append(
            f"| {table} | {name} | {_f(p['mpjpe_mm'])} | {_f(p['pa_mpjpe_mm'])} | {_f(v['psnr'], 2)} | "
            f"{_f(v['ssim'], 3)} | {_f(v['lpips'], 3)} | {_f(v['box_psnr'], 2)} | {train_s:.0f} | {total:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    print()
    print(text)
    out = args.out or ws / "reports" / "paper_tables.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# GST paper tables on the synthetic demo scene\n\n" + text)


if __name__ == "__main__":
    main()
