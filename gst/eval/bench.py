"""Run time against error for GST variants, in one run (docs/evaluate.md, "bench").

A variant is a backbone preset, an input size and a Gaussian count (vertex preset). Each one is
trained with the same short budget on the scene's training split (`gst.eval.split`), or taken
as-is from a checkpoint, then timed (median over repeats of one batch of real crops, after a
warm-up; all variants are timed round-robin, so load from other processes falls on each alike)
and scored with the evaluator on the test split: MPJPE on test frames, PSNR of the
held-out cameras. Every variant gives two rows: pose-only (the Gaussian tokens are skipped) and
full (network plus posed Gaussians); their errors are the same model's.
"""

from __future__ import annotations

import csv
import io
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from gst.atomic import atomic_write
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.report import figure_text as _f
from gst.eval.split import FinetuneConfig, Split, finetune
from gst.model.presets import get_preset
from gst.train.recipe import build_network, make_task
from gst.train.steps import predict
from gst.train.views import CropSet

__all__ = [
    "Variant",
    "BenchRow",
    "time_inference",
    "run_bench",
    "write_bench_table",
    "write_pareto_plot",
]


@dataclass(frozen=True)
class Variant:
    name: str
    preset: str = "tiny"
    image_size: tuple[int, int] | None = None  # ViT input (H, W); None: the preset's
    vertex_preset: str | None = (
        None  # Gaussian count: "1723", "3445", "6890", "full"; None: the preset's
    )
    checkpoint: str | None = (
        None  # use these weights as they are (no training); must match the variant
    )
    # landmark tokens (gst.model.landmarks): 0 = none (the paper's image-only network), else
    # the number of BlazePose landmarks taken (33 or the 12 limb ones); per-landmark tokens
    landmarks: int = 0
    landmark_point_tokens: bool = False
    # rounds of reprojection feedback after the SMPL head (gst.model.refine), with landmarks
    landmark_refine: int = 0

    def config(self):
        cfg = get_preset(self.preset)
        if self.image_size is not None:
            cfg = replace(cfg, vit=replace(cfg.vit, image_size=tuple(self.image_size)))
        if self.vertex_preset is not None:
            cfg = replace(cfg, vertex_preset=self.vertex_preset)
        if self.landmarks:
            cfg = replace(
                cfg,
                landmark_tokens=True,
                num_landmarks=self.landmarks,
                landmark_point_tokens=self.landmark_point_tokens,
                landmark_refine=self.landmark_refine,
            )
        return cfg


@dataclass
class BenchRow:
    variant: str
    preset: str
    input_size: str
    gaussians: int
    output: str  # "pose-only" | "full"
    landmarks: int  # landmarks the network takes (0: image only)
    params_m: float
    training: str  # how the weights were obtained
    ms_per_batch: float
    ms_per_crop: float
    fps: float
    mpjpe_mm: float | None
    pa_mpjpe_mm: float | None
    psnr: float | None  # held-out cameras, test frames (full rows only)
    not_finite: int = 0  # crops whose prediction was not finite: left out of the errors


def time_inference(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median seconds of `fn()` over `repeats` calls after `warmup` untimed calls."""
    return round_robin_medians([fn], repeats, warmup=warmup)[0][0]


def round_robin_medians(
    calls: Sequence[Callable[[], object]], repeats: int, warmup: int = 1, warm_each: bool = True
) -> list[tuple[float, object]]:
    """(median wall seconds, last result) of each call over `repeats` rounds that call every one
    in turn, so load from other processes falls on all of them alike; first `warmup` untimed
    rounds of every call (`warm_each`), or of the first call only (calls that share their
    first-call costs: lazy imports, allocator, caches, the page cache)."""
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    for _ in range(warmup):
        for fn in calls if warm_each else calls[:1]:
            fn()
    times: list[list[float]] = [[] for _ in calls]
    out: list = [None] * len(calls)
    for _ in range(repeats):
        for k, fn in enumerate(calls):
            t0 = time.perf_counter()
            out[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return [(statistics.median(t), o) for t, o in zip(times, out, strict=True)]


def _interleaved_medians(calls: list[Callable[[], object]], repeats: int) -> list[float]:
    """Median seconds of every call, timed round-robin (one warm-up each, then `repeats` rounds
    over all calls), so load from other processes falls on every variant alike."""
    return [sec for sec, _ in round_robin_medians(calls, repeats)]


def run_bench(
    variants: list[Variant],
    crops: CropSet,
    split: Split,
    body,
    body_spec: str,
    train: FinetuneConfig,
    *,
    lpips=None,
    repeats: int = 5,
    batch: int = 8,
    render_size: int = 64,
    max_groups: int | None = 16,
    log: Callable[[str], None] = print,
    load_checkpoint_fn=None,
) -> list[BenchRow]:
    """Train (or load) and score every variant, then time them all round-robin; returns two rows
    per variant (pose-only, full)."""
    test = torch.nonzero(
        (crops.frame >= split.test_frames[0]) & (crops.frame < split.test_frames[1])
    )[:, 0]
    timing_rows = test[:batch] if len(test) >= batch else torch.arange(min(batch, len(crops)))
    images, K = crops.images[timing_rows], crops.K[timing_rows]
    landmarks = None if crops.landmarks is None else crops.landmarks[timing_rows]
    eval_cfg = EvalConfig(
        heldout_cameras=split.heldout_cameras,
        render_size=render_size,
        frames=split.test_frames,
        max_groups=max_groups,
        side_by_side_groups=0,
    )
    pending, calls = [], []
    for v in variants:
        if v.checkpoint is not None:
            if load_checkpoint_fn is None:
                raise ValueError(f"variant {v.name}: a checkpoint needs load_checkpoint_fn")
            net, ids, groups = load_checkpoint_fn(v.checkpoint)
            if net.cfg.name != v.preset or tuple(net.cfg.image_size) != tuple(
                v.config().image_size
            ):
                raise ValueError(
                    f"variant {v.name}: checkpoint {v.checkpoint} is preset {net.cfg.name} at "
                    f"{net.cfg.image_size}, the variant asks for {v.preset} at "
                    f"{v.config().image_size}"
                )
            how = "checkpoint as is"
        else:
            net, ids, groups = build_network(v.config(), body)
            secs = finetune(
                net, body, ids, groups, crops, split, train, body_spec=body_spec, lpips=lpips
            )
            how = f"{train.steps} steps {train.mode} from scratch ({secs:.0f} s)"
        net.eval()
        task = make_task(body, ids, net.cfg, crops.crop_size, train.weights)
        res = evaluate_model(net, task, crops, eval_cfg, joint_names=body.joint_names, lpips=None)
        nv_summary = res.summary.novel_view
        pose, nv = res.summary.pose.overall, nv_summary.heldout if nv_summary else {}
        log(
            f"bench {v.name}: MPJPE {_f(pose['mpjpe_mm'])} mm, "
            f"held-out PSNR {nv.get('psnr')} ({how})"
        )
        params_m = round(sum(p.numel() for p in net.parameters()) / 1e6, 2)
        timed = net
        if not all(bool(torch.isfinite(p).all()) for p in net.parameters()):
            # a diverged network is scored n/a above; the body model refuses its NaN output, so
            # its speed (which no weight changes) is timed on a fresh network of the same config
            log(f"bench {v.name}: its weights are not finite; timed on a fresh {v.preset}")
            timed, _, _ = build_network(net.cfg, body)
            timed.eval()
        for output, with_g in (("pose-only", False), ("full", True)):

            def call(net=timed, task=task, with_g=with_g):
                with torch.no_grad():
                    predict(net, task, images, K, with_gaussians=with_g, landmarks=landmarks)

            calls.append(call)
            pending.append(
                BenchRow(
                    v.name,
                    net.cfg.name,
                    f"{net.cfg.image_size[0]}x{net.cfg.image_size[1]}",
                    len(ids),
                    output,
                    net.cfg.num_landmarks if net.landmark_encoder is not None else 0,
                    params_m,
                    how,
                    0.0,
                    0.0,
                    0.0,
                    pose["mpjpe_mm"],
                    pose["pa_mpjpe_mm"],
                    nv.get("psnr") if with_g else None,
                    pose["n_not_finite"],
                )
            )
    for row, sec in zip(pending, _interleaved_medians(calls, repeats), strict=True):
        row.ms_per_batch, row.fps = 1000 * sec, len(timing_rows) / sec
        row.ms_per_crop = row.ms_per_batch / len(timing_rows)
        log(
            f"bench {row.variant} {row.output}: {row.ms_per_batch:.1f} ms per batch of "
            f"{len(timing_rows)}"
        )
    return pending


def write_bench_table(out: Path, rows: list[BenchRow], header: str) -> None:
    """table.csv (one row per variant and output) and table.md (the same, plus `header`)."""
    fields = list(asdict(rows[0])) if rows else [f for f in BenchRow.__dataclass_fields__]

    def write_csv(tmp: str) -> None:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            for r in rows:
                w.writerow(asdict(r))

    atomic_write(out / "table.csv", write_csv)
    base = {r.variant: r.ms_per_batch for r in rows if r.output == "pose-only"}
    ref = min(base.values()) if base else None
    lines = [
        header,
        "",
        "| variant | preset | input | Gaussians | landmarks | output | params (M) | ms/crop | "
        "crops/s | time vs fastest | MPJPE (mm) | PA-MPJPE (mm) | crops not finite (left out) | "
        "PSNR held-out (dB) | weights |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.variant} | {r.preset} | {r.input_size} | {r.gaussians} | {r.landmarks or '-'} | "
            f"{r.output} | {r.params_m:.2f} | {r.ms_per_crop:.2f} | {r.fps:.1f} | "
            f"{r.ms_per_batch / ref:.2f}x | {_f(r.mpjpe_mm)} | {_f(r.pa_mpjpe_mm)} | "
            f"{r.not_finite} | {_f(r.psnr, 2)} | {r.training} |"
        )
    text = "\n".join(lines) + "\n\n![Pareto](pareto.png)\n"
    atomic_write(out / "table.md", lambda tmp: Path(tmp).write_text(text))


def _pareto(points: list[tuple[float, float]], lower_better: bool) -> list[int]:
    """Indices of points not dominated in (time lower, error lower / score higher)."""
    keep = []
    for i, (t, e) in enumerate(points):
        better = lambda a, b: a < b if lower_better else a > b  # noqa: E731
        dominated = any(
            (t2 <= t and (better(e2, e) or e2 == e)) and (t2 < t or better(e2, e))
            for j, (t2, e2) in enumerate(points)
            if j != i
        )
        if not dominated:
            keep.append(i)
    return keep


def write_pareto_plot(path: Path, rows: list[BenchRow]) -> None:
    """Two panels: ms per crop against MPJPE (all rows) and against held-out PSNR (full rows);
    the Pareto front of each is drawn as a line; landmark models are drawn with a star."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    fig.subplots_adjust(wspace=0.3)
    names = list(dict.fromkeys(r.variant for r in rows))
    colours = {n: plt.cm.tab10(i % 10) for i, n in enumerate(names)}
    for ax, key, label, lower in (
        (axes[0], "mpjpe_mm", "MPJPE (mm), lower is better", True),
        (axes[1], "psnr", "held-out PSNR (dB), higher is better", False),
    ):
        pts = [(r, getattr(r, key)) for r in rows if getattr(r, key) is not None]
        for r, e in pts:
            marker = ("*" if r.landmarks else "o") if r.output == "full" else "s"
            ax.scatter(
                r.ms_per_crop,
                e,
                color=colours[r.variant],
                marker=marker,
                s=80 if r.landmarks else 36,
                label=f"{r.variant} ({r.output})",
            )
        front = _pareto([(r.ms_per_crop, e) for r, e in pts], lower)
        fr = sorted((pts[i][0].ms_per_crop, pts[i][1]) for i in front)
        if fr:
            ax.plot(*zip(*fr, strict=True), "k--", lw=1, label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlabel("network run time per crop (ms, median over repeats of one batch, log scale)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(buf.getvalue()))
