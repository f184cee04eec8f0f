"""Write the evaluation report: summary.json, report.md, per-record CSVs, PNG plots and a
side-by-side image (layout in docs/evaluate.md). Every file is written atomically."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from gst.atomic import atomic_write
from gst.eval.evaluate import EvalResult
from gst.eval.summary import VIEW_KEYS
from gst.train.views import CropSet

__all__ = ["write_report", "side_by_side_image", "write_text", "write_png"]


def write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def write_png(path: Path, rgb: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"could not encode {path}")
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(buf.tobytes()))


def _save_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(buf.getvalue()))


def figure_text(v, digits: int = 1) -> str:
    """A figure for a report or a log line: 'n/a' where there is none (None, NaN or inf)."""
    return (
        "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"
    )


_f = figure_text


def _grouped_bars(ax, groups: list[str], series: dict[str, list], ylabel: str, title: str) -> None:
    width = 0.8 / max(1, len(series))
    x = np.arange(len(groups))
    for k, (name, values) in enumerate(series.items()):
        ax.bar(
            x + (k - (len(series) - 1) / 2) * width,
            [np.nan if v is None else v for v in values],
            width,
            label=name,
        )
    ax.set_xticks(x, groups, rotation=30, ha="right")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    if len(series) > 1:
        ax.legend(fontsize=8)


def _series(summaries: dict[str, dict], section: str, table: str, keys: list[str], metric: str):
    """{run: [summary[section][table][key][metric] per key, None where the run lacks it]}."""
    return {
        n: [s[section][table].get(k, {}).get(metric) for k in keys] for n, s in summaries.items()
    }


# metric of a bar panel -> (the summaries' section that holds it, its axis label)
_BAR_METRICS = {
    "mpjpe_mm": ("pose", "MPJPE (mm)"),
    "pa_mpjpe_mm": ("pose", "PA-MPJPE (mm)"),
    "psnr": ("novel_view", "PSNR (dB)"),
}


def _panel(
    summaries: dict[str, dict], table: str, keys: list[str], metric: str, title: str, labels=None
):
    """One `_grouped_bars` panel (its arguments after the axes): `metric` of each run's
    table[key] per key, the groups named by `labels` (default: the keys)."""
    section, ylabel = _BAR_METRICS[metric]
    return (
        keys if labels is None else labels,
        _series(summaries, section, table, keys, metric),
        ylabel,
        title,
    )


def _bar_figure(path: Path, panels: list[tuple]) -> None:
    """A row of `_grouped_bars` panels (each given as its arguments after the axes)."""
    import matplotlib.pyplot as plt

    wide = len(panels) > 1
    fig, axes = plt.subplots(1, len(panels), figsize=(11 if wide else 6, 3.6), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        _grouped_bars(ax, *panel)
    _save_figure(fig, path)


def _plots(out: Path, summaries: dict[str, dict]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")

    cams = sorted({c for s in summaries.values() for c in s["pose"]["per_camera"]})
    has_views = all("novel_view" in s for s in summaries.values())
    panels = [_panel(summaries, "per_camera", cams, "mpjpe_mm", "pose error per input camera")]
    if has_views:
        tcams = sorted(
            {c for s in summaries.values() for c in s["novel_view"]["per_target_camera"]}
        )
        held = {
            c
            for s in summaries.values()
            for c, v in s["novel_view"]["per_target_camera"].items()
            if v["heldout"]
        }
        labels = [c + (" (held out)" if c in held else "") for c in tcams]
        title = "novel-view PSNR per target camera"
        panels.append(_panel(summaries, "per_target_camera", tcams, "psnr", title, labels))
    _bar_figure(out / "per_camera.png", panels)

    parts = list(next(iter(summaries.values()))["pose"]["per_part"])
    _bar_figure(
        out / "per_part.png",
        [
            _panel(summaries, "per_part", parts, "mpjpe_mm", "per body part (root-aligned)"),
            _panel(
                summaries, "per_part", parts, "pa_mpjpe_mm", "per body part (Procrustes-aligned)"
            ),
        ],
    )

    motions = sorted({m for s in summaries.values() for m in s["pose"]["per_motion"]})
    panels = [_panel(summaries, "per_motion", motions, "mpjpe_mm", "pose error per motion")]
    if has_views:
        panels.append(
            _panel(summaries, "per_motion", motions, "psnr", "held-out-view PSNR per motion")
        )
    _bar_figure(out / "per_motion.png", panels)
    return ["per_camera.png", "per_part.png", "per_motion.png"]


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    cv2.putText(img, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 0), 1, cv2.LINE_AA)
    return img


def side_by_side_image(result: EvalResult, crops: CropSet) -> np.ndarray | None:
    """Per kept input: top row the input crop then the prediction rendered into every other view,
    bottom row what those cameras saw (background removed). Held-out views are marked [H]."""
    if result.views is None or not result.side_by_side:
        return None
    v = result.views
    rows = []
    by_input: dict[int, list[int]] = {}
    for k in result.side_by_side:
        if k in v.images:  # a pair whose prediction was not finite has no render (counted)
            by_input.setdefault(int(v.inputs[k]), []).append(k)
    if not by_input:
        return None
    width = max(len(ks) for ks in by_input.values()) + 1
    for inp, ks in by_input.items():
        size = v.images[ks[0]][0].shape[0]
        blank = np.zeros((size, size, 3), np.uint8)
        inp_img = cv2.resize(crops.images[inp].numpy(), (size, size), interpolation=cv2.INTER_AREA)
        top = [_label(inp_img, f"input {crops.camera_names[int(crops.camera[inp])]}")]
        bottom = [_label(blank, "truth ->")]
        for k in ks:
            cam = crops.camera_names[int(v.camera[k])] + (" [H]" if v.heldout[k] else "")
            render, target = v.images[k]
            top.append(_label(render, f"pred {cam}"))
            bottom.append(_label(target, f"truth {cam}"))
        top += [blank] * (width - len(top))
        bottom += [blank] * (width - len(bottom))
        rows += [np.concatenate(top, 1), np.concatenate(bottom, 1)]
    return np.concatenate(rows, 0)


def _write_csv(path: Path, header: list[str], rows: Iterable[list]) -> None:
    """A CSV file of `header` then `rows`, written atomically."""

    def write(tmp: str) -> None:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(rows)

    atomic_write(path, write)


def _write_csvs(out: Path, result: EvalResult, crops: CropSet, motions) -> None:
    p = result.pose
    motion_of = (
        (lambda r: str(motions[int(crops.truth["truth_row"][r])]))
        if motions is not None and "truth_row" in crops.truth
        else (lambda r: "all")
    )
    _write_csv(
        out / "per_crop.csv",
        ["row", "camera", "frame", "motion", "mpjpe_mm", "pa_mpjpe_mm", "pve_mm", "pa_pve_mm"],
        (
            [
                int(r),
                crops.camera_names[int(p.camera[i])],
                int(p.frame[i]),
                motion_of(int(r)),
                f"{1000 * p.mpjpe[i]:.3f}",
                f"{1000 * p.pa_mpjpe[i]:.3f}",
                "" if p.pve is None else f"{1000 * p.pve[i]:.3f}",
                "" if p.pa_pve is None else f"{1000 * p.pa_pve[i]:.3f}",
            ]
            for i, r in enumerate(p.rows)
        ),
    )
    if result.views is None:
        return
    v = result.views
    keys = VIEW_KEYS
    _write_csv(
        out / "per_view.csv",
        ["input_row", "target_row", "input_camera", "target_camera", "heldout", "frame", *keys],
        (
            [
                int(v.inputs[i]),
                int(v.targets[i]),
                crops.camera_names[int(crops.camera[v.inputs[i]])],
                crops.camera_names[int(v.camera[i])],
                bool(v.heldout[i]),
                int(crops.frame[v.targets[i]]),
                *(f"{getattr(v, k)[i]:.5f}" for k in keys),
            ]
            for i in range(len(v.inputs))
        ),
    )


_HEADLINE = [
    ("MPJPE (mm)", "pose", "overall", "mpjpe_mm", 1),
    ("PA-MPJPE (mm)", "pose", "overall", "pa_mpjpe_mm", 1),
    ("PVE (mm)", "pose", "overall", "pve_mm", 1),
    ("PA-PVE (mm)", "pose", "overall", "pa_pve_mm", 1),
    ("crops with left/right mirrored landmarks", "pose", "overall", "mirrored_landmarks", 0),
    ("MPJPE (mm) without those crops", "pose", "overall", "mpjpe_mm_not_mirrored", 1),
    ("PSNR (dB), held-out, full crop", "novel_view", "heldout", "psnr", 2),
    ("SSIM, held-out, full crop", "novel_view", "heldout", "ssim", 3),
    ("LPIPS, held-out, full crop", "novel_view", "heldout", "lpips", 3),
    ("PSNR (dB), held-out, SHERF box", "novel_view", "heldout", "box_psnr", 2),
    ("SSIM, held-out, SHERF box", "novel_view", "heldout", "box_ssim", 3),
    ("LPIPS, held-out, SHERF box", "novel_view", "heldout", "box_lpips", 3),
    ("silhouette IoU, held-out", "novel_view", "heldout", "silhouette_iou", 3),
    ("PSNR (dB), held-out, others' pixels left out", "novel_view", "heldout", "psnr_unoccluded", 2),
    (
        "silhouette IoU, held-out, others' pixels left out",
        "novel_view",
        "heldout",
        "silhouette_iou_unoccluded",
        3,
    ),
    ("PSNR (dB), other training views", "novel_view", "trained_views", "psnr", 2),
]


def _get(s: dict, a: str, b: str, c: str):
    return s.get(a, {}).get(b, {}).get(c)


# what the SHERF-style box is (EvalCounts.sherf_box)
SHERF_BOXES = {
    "mesh": "the truth body's projected 3D box (5 cm margin)",
    "joints": "the projected 3D box of the reference joints (15 cm margin: no truth mesh; not "
    "comparable with SHERF's figures)",
}


def _markdown(summaries: dict[str, dict], meta: dict, plots: list[str], has_sbs: bool) -> str:
    names = list(summaries)
    first = summaries[names[0]]
    models = ", ".join(f"`{n}` ({meta.get('models', {}).get(n, '?')})" for n in names)
    reference = meta.get("reference", "synthetic truth")
    fused = reference != "synthetic truth"  # a real scene: agreement with the rig, not error
    heldout = first["counts"]["heldout_cameras"]
    title = "the rig's fused bodies" if fused else "the synthetic truth"
    lines = [
        f"# Evaluation against {title}",
        "",
        f"Scene `{meta.get('scene', '?')}`; models: {models}. "
        f"{first['counts']['pose_crops']} crops with {'a fused body' if fused else 'truth'}; "
        f"{first['counts']['view_pairs']} novel-view pairs "
        f"rendered at {first['counts']['render_size']} px; held-out cameras: "
        f"{', '.join(first['counts']['heldout_cameras']) or 'none'}.",
        "",
    ]
    if meta.get("note"):
        lines += [meta["note"], ""]
    if heldout and not first.get("novel_view", {}).get("heldout", {}).get("n"):
        lines += [
            f"No novel-view pair has its target in a held-out camera ({', '.join(heldout)}): "
            "no scored person was seen there, so the held-out rows are left out.",
            "",
        ]
    lines += ["| metric | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for label, a, b, c, d in _HEADLINE:
        vals = [_get(summaries[n], a, b, c) for n in names]
        if all(v is None for v in vals):
            continue
        lines.append(f"| {label} | " + " | ".join(_f(v, d) for v in vals) + " |")
    bad = [_get(summaries[n], "pose", "overall", "n_not_finite") or 0 for n in names]
    if any(bad):  # the means above cover only the finite crops: say how many are not in them
        lines.append(
            "| crops whose prediction is not finite (left out of the errors above) | "
            + " | ".join(
                f"{v} of {_get(summaries[n], 'pose', 'overall', 'n')}"
                for n, v in zip(names, bad, strict=True)
            )
            + " |"
        )
    last = names[-1]
    s = summaries[last]
    lines += [
        "",
        f"## Breakdowns (`{last}`)",
        "",
        "### Per input camera (pose)",
        "",
        "| camera | n | MPJPE | PA-MPJPE | PVE |",
        "|---|---|---|---|---|",
    ]
    for cam, v in s["pose"]["per_camera"].items():
        lines.append(
            f"| {cam} | {v['n']} | {_f(v['mpjpe_mm'])} | {_f(v['pa_mpjpe_mm'])} | "
            f"{_f(v.get('pve_mm'))} |"
        )
    lines += [
        "",
        "### Per motion",
        "",
        "| motion | crops | MPJPE | PA-MPJPE | held-out pairs | held-out PSNR | held-out LPIPS |",
        "|---|---|---|---|---|---|---|",
    ]
    for m, v in s["pose"]["per_motion"].items():
        # the image columns average view pairs, not crops: each has its own count
        nv = s.get("novel_view", {}).get("per_motion", {}).get(m, {})
        lines.append(
            f"| {m} | {v['n']} | {_f(v['mpjpe_mm'])} | {_f(v['pa_mpjpe_mm'])} | "
            f"{nv.get('n', 0)} | {_f(nv.get('psnr'), 2)} | {_f(nv.get('lpips'), 3)} |"
        )
    lines += ["", "### Per body part", "", "| part | MPJPE | PA-MPJPE |", "|---|---|---|"]
    for part, v in s["pose"]["per_part"].items():
        lines.append(f"| {part} | {_f(v['mpjpe_mm'])} | {_f(v['pa_mpjpe_mm'])} |")
    if "novel_view" in s:
        lines += [
            "",
            "### Per target camera (novel views)",
            "",
            "| camera | held out | n | PSNR | SSIM | LPIPS "
            "| box PSNR | box SSIM | box LPIPS | IoU |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for cam, v in s["novel_view"]["per_target_camera"].items():
            lines.append(
                f"| {cam} | {'yes' if v['heldout'] else 'no'} | {v['n']} | {_f(v['psnr'], 2)} | "
                f"{_f(v['ssim'], 3)} | {_f(v['lpips'], 3)} | {_f(v['box_psnr'], 2)} | "
                f"{_f(v['box_ssim'], 3)} | "
                f"{_f(v['box_lpips'], 3)} | {_f(v['silhouette_iou'], 3)} |"
            )
    lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    if has_sbs:
        lines += [
            "",
            "## Side by side",
            "",
            "![side by side](side_by_side.png)",
            "",
            f"Model `{last}`. Per input: top row the input crop, then the prediction rendered "
            "into every other camera of the same frame ([H] = held-out camera); bottom row what "
            "those cameras saw, background removed.",
        ]
    box = SHERF_BOXES[summaries[last]["counts"].get("sherf_box") or "mesh"]
    lines += [
        "",
        "MPJPE is pelvis-aligned, PA-MPJPE after a similarity Procrustes fit, PVE/PA-PVE the "
        "same on all mesh vertices; all in the world frame through the input camera. Novel views: "
        "prediction rendered on black vs image x mask; full crop = the whole rendered crop, SHERF "
        f"box = inside {box} for PSNR and its 2D bounding rectangle for SSIM/LPIPS (LPIPS v0.1 "
        "AlexNet). Formats: docs/evaluate.md.",
    ]
    return "\n".join(lines) + "\n"


def write_report(
    out: Path,
    results: dict[str, EvalResult],
    crops: CropSet,
    meta: dict,
    motions: np.ndarray | None = None,
) -> dict:
    """Write the report of one or more evaluated models (the last one is detailed). Returns the
    summary.json content: {"meta": ..., "models": {name: summary}}."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summaries = {n: r.summary.to_dict() for n, r in results.items()}
    plots = _plots(out, summaries)
    last = list(results)[-1]
    sbs = side_by_side_image(results[last], crops)
    if sbs is not None:
        write_png(out / "side_by_side.png", sbs)
    _write_csvs(out, results[last], crops, motions)
    doc = {"format": "gst-capture/evaluation", "version": 1, "meta": meta, "models": summaries}
    write_text(out / "summary.json", json.dumps(doc, indent=2, default=float, allow_nan=False))
    write_text(out / "report.md", _markdown(summaries, meta, plots, sbs is not None))
    return doc
