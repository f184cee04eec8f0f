"""The GST paper's Table 1 and Table 5 on our synthetic world, in one run, with an equal budget.

From the pretrained model (models/pretrain.pt) and the scene's extracted crops, prepared as the
`train` stage prepares them (landmarks, detected joints, anchors, occluders, distillation
targets from the rig refitted without held-out data), every row is fine-tuned with the same
step budget on the same training split (earlier frames, training cameras) and scored by the
same evaluator on the test split (the last `--test-fraction` of the frames, which no row and no
distillation target saw; pose from every camera's single image, novel views rendered into the
held-out camera):

  Table 1: pretrained only | 2D fine-tuned (2D joint labels) | 3D fine-tuned (3D labels)
           | GST multi-view, the paper's objective alone | + anchors and detected joints (ours)
           | + distillation from the rig (ours; the train stage's default)
  Table 5: the default without LPIPS | without tightness | without alpha | without detected
           joints | without anchors | distillation alone (no anchors, no detected joints)

Multi-view rows train as the train stage does (Gaussian head at --lr, the rest at --body-lr);
the 2D/3D rows train everything at --supervised-lr. Columns: MPJPE and PA-MPJPE (mm), PSNR /
SSIM / LPIPS / silhouette IoU in the held-out camera (full crop), the SHERF box PSNR, and each
row's run time (training + evaluation). Prints the markdown table and writes it to --out.

    python benchmarks/bench_paper_tables.py --workspace workspace/demo [--steps 200] [--threads 1]
"""

from __future__ import annotations

import copy
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from calibration.formats import read_rig  # noqa: E402
from gst.atomic import atomic_write_text  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.eval.evaluate import EvalConfig, evaluate_model  # noqa: E402
from gst.eval.split import FinetuneConfig, finetune, frame_split  # noqa: E402
from gst.lift.rehearsal import PriorRehearsal  # noqa: E402
from gst.lift.teacher import RigTeacher  # noqa: E402
from gst.metrics.lpips import load_lpips  # noqa: E402
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint  # noqa: E402
from gst.train.losses import LossWeights  # noqa: E402
from gst.train.recipe import make_task  # noqa: E402
from gst.train.scene_training import TrainSettings, prepare_crops  # noqa: E402
from synth.truth import read_scene_truth  # noqa: E402

DEFAULT = LossWeights()  # the train stage's weights: paper terms + anchors, joints, distillation
OFF = {"anchor": 0.0, "keypoints": 0.0, "distill_joints": 0.0, "distill_root": 0.0,
       "distill_params": 0.0}  # fmt: skip
PAPER = DEFAULT.model_copy(update=OFF)  # LPIPS 0.01, alpha 0.1, tightness 0.1 and nothing else
NO_DISTILL = DEFAULT.model_copy(update={k: 0.0 for k in OFF if k.startswith("distill")})


def _without(**zero) -> LossWeights:
    return DEFAULT.model_copy(update=zero)


# (table, row, fit_gst mode, loss weights, whether the landmark prior is rehearsed beside each
# step as the train stage does by default: train.rehearsal, gst.lift.rehearsal)
ROWS = [
    ("Table 1", "pretrained only", None, DEFAULT, False),
    ("Table 1", "2D fine-tuned", "2d", DEFAULT, False),
    ("Table 1", "3D fine-tuned", "3d", DEFAULT, False),
    ("Table 1", "GST multi-view (paper objective)", "multiview", PAPER, False),
    ("Table 1", "GST + anchors + detected joints", "multiview", NO_DISTILL, False),
    ("Table 1", "GST + anchors + joints + distillation", "multiview", DEFAULT, False),
    ("Table 1", "the same + prior rehearsal (default)", "multiview", DEFAULT, True),
    ("Table 5", "default w/o LPIPS", "multiview", _without(lpips=0.0), True),
    ("Table 5", "default w/o tightness", "multiview", _without(tightness=0.0), True),
    ("Table 5", "default w/o alpha", "multiview", _without(alpha=0.0), True),
    ("Table 5", "default w/o detected joints", "multiview", _without(keypoints=0.0), True),
    ("Table 5", "default w/o anchors", "multiview", _without(anchor=0.0), True),
    (
        "Table 5",
        "distillation and rehearsal alone",
        "multiview",
        _without(anchor=0.0, keypoints=0.0),
        True,
    ),
]


def _teaches_appearance(settings: TrainSettings, weights: LossWeights) -> bool:
    """Whether the train stage, with these loss weights, poses the Gaussians on the rig
    teacher's body (`appearance_on_teacher` with distillation on)."""
    distils = any(getattr(weights, k) > 0 for k in OFF if k.startswith("distill"))
    return settings.distill and settings.appearance_on_teacher and distils


def _f(v, d=1) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument(
        "--workspace", type=Path, default=Path("workspace/demo"), help="scene workspace (synthetic)"
    )
    ap.add_argument("--steps", type=int, default=200, help="fine-tuning steps of every row")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=1e-3, help="multi-view rows: the Gaussian head")
    ap.add_argument("--body-lr", type=float, default=3e-4, help="multi-view rows: the rest")
    ap.add_argument("--supervised-lr", type=float, default=1e-4, help="2D / 3D rows")
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
    unknown = sorted(set(args.rows or ()) - {row[1] for row in ROWS})
    if unknown:  # (a mistyped name ran nothing, after the costly preparation, then crashed)
        ap.error(f"--rows: no such row(s) {unknown}; rows: {[row[1] for row in ROWS]}")
    if args.threads:
        torch.set_num_threads(args.threads)
    ws = args.workspace
    ckpt = load_checkpoint(ws / "models" / "pretrain.pt")
    body = load_body_model(ckpt.body_model)
    base = network_from_checkpoint(ckpt)
    settings = TrainSettings(heldout_frames=args.test_fraction)
    teacher = RigTeacher(
        ws / "fused" / "bodies.parquet",
        ws / "crops" / "crops.h5",
        read_rig(ws / "calibration" / "rig.json", "rig"),
    )
    prepared = prepare_crops(
        settings, ws / "crops" / "crops.h5", ws / "synth",
        feed_landmarks=base.landmark_encoder is not None, teacher=teacher,
        work=ws / "models" / "paper_tables_teacher",
    )  # fmt: skip
    crops, heldout = prepared.crops, tuple(prepared.heldout_cameras)
    truth = read_scene_truth(ws / "synth")
    split = frame_split(crops, heldout, args.test_fraction)
    assert split.test_frames[0] == prepared.first_heldout_frame  # one split for every term
    ids, groups = ckpt.vertex_ids.numpy(), ckpt.group_index.numpy()
    lpips = load_lpips()
    vertices = truth.vertices(body) if ckpt.body_model == truth.body_model else None
    eval_cfg = EvalConfig(
        heldout_cameras=heldout,
        render_size=args.render_size,
        frames=split.test_frames,
        side_by_side_groups=0,
    )
    print(
        f"preset {base.cfg.name} (landmarks: "
        f"{base.cfg.num_landmarks if base.cfg.landmark_tokens else 'none'}), "
        f"{torch.get_num_threads()} threads; {args.steps} steps x batch {args.batch} per row; "
        f"train: {len(split.train_rows)} crops of frames < {split.test_frames[0]} "
        f"outside {heldout}; "
        f"test: frames {split.test_frames[0]}-{split.test_frames[1] - 1}; novel views at "
        f"{args.render_size} px",
        flush=True,
    )
    results = []
    t_all = time.perf_counter()
    for table, name, mode, weights, rehearse in ROWS:
        if args.rows and name not in args.rows:
            continue
        t0 = time.perf_counter()
        net = copy.deepcopy(base)
        train_s = 0.0
        if mode is not None:
            multiview = mode == "multiview"
            cfg = FinetuneConfig(
                mode=mode,
                steps=args.steps,
                batch_size=args.batch,
                lr=args.lr if multiview else args.supervised_lr,
                body_lr=args.body_lr if multiview else None,
                weights=weights,
                landmark_dropout=settings.landmark_dropout if multiview else 0.0,
                # as the train stage: the Gaussians on the rig's body where it distils
                appearance_on_teacher=multiview and _teaches_appearance(settings, weights),
            )
            rehearsal = (
                PriorRehearsal(
                    body, net, weight=settings.rehearsal, batch_size=settings.rehearsal_batch,
                    crop_size=crops.crop_size,
                )
                if rehearse and net.landmark_encoder is not None
                else None
            )  # fmt: skip
            train_s = finetune(
                net, body, ids, groups, crops, split, cfg, body_spec=ckpt.body_model,
                lpips=lpips, rehearsal=rehearsal,
            )  # fmt: skip
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
        p, v = res.summary.pose.overall, res.summary.novel_view.heldout
        results.append((table, name, p, v, train_s, time.perf_counter() - t0))
        print(
            f"{table} {name}: MPJPE {_f(p['mpjpe_mm'])} PA-MPJPE {_f(p['pa_mpjpe_mm'])} "
            f"({p['n_not_finite']} of {p['n']} crops not finite, left out) "
            f"PSNR {_f(v['psnr'], 2)} IoU {_f(v['silhouette_iou'], 3)} SSIM {_f(v['ssim'], 3)} "
            f"LPIPS {_f(v['lpips'], 3)} ({train_s:.0f} s training, "
            f"{time.perf_counter() - t0:.0f} s total)",
            flush=True,
        )
    lines = [
        f"Fine-tuning budget per row: {args.steps} steps x batch {args.batch}; total "
        f"{time.perf_counter() - t_all:.0f} s on CPU ({torch.get_num_threads()} threads). Pose on "
        f"{res.summary.counts.pose_crops} test crops (frames {split.test_frames[0]}-"
        f"{split.test_frames[1] - 1}, never trained on); novel views: {v['n']} held-out-camera "
        "pairs.",
        "",
        "| table | row | MPJPE (mm) | PA-MPJPE (mm) | crops not finite (left out) | PSNR (dB) | "
        "IoU | SSIM | LPIPS | box PSNR (dB) | train s | total s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for table, name, p, v, train_s, total in results:
        lines.append(
            f"| {table} | {name} | {_f(p['mpjpe_mm'])} | {_f(p['pa_mpjpe_mm'])} | "
            f"{p['n_not_finite']} | {_f(v['psnr'], 2)} | {_f(v['silhouette_iou'], 3)} | "
            f"{_f(v['ssim'], 3)} | "
            f"{_f(v['lpips'], 3)} | {_f(v['box_psnr'], 2)} | {train_s:.0f} | {total:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    print()
    print(text)
    out = args.out or ws / "reports" / "paper_tables.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "# GST paper tables on the synthetic demo scene\n\n" + text)


if __name__ == "__main__":
    main()
