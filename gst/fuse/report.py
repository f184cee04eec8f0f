"""The fusion report: reprojection per camera and landmark, bone lengths, gap share, truth.

`reports/fuse/summary.json` holds every number (strict JSON: a value that is not defined, e.g.
MPJPE with no fused body paired with the truth, is null, not NaN); `reports/fuse/report.md`
the tables people read; `reports/fuse/bone_lengths.png` the limb lengths over time. Limb
lengths are given three times: from the body fit (one shape per person, so constant by
construction: a check of the pipeline, not of the data), from the triangulated landmarks (the
distance between two noisy points), and from a fit of every frame on its own with the shape
free (gst.fuse.consistency: the measurement of how steady the rig's 3D is). Coefficients of
variation are given plain (std / mean) and robust (1.4826 MAD / median, which one wrong frame
cannot dominate).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gst.atomic import atomic_write, finite_json
from gst.body.markers import BLAZEPOSE_NAMES
from gst.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS
from gst.fuse.fit import PersonFit
from gst.fuse.tables import JointEvidence
from gst.fuse.triangulate import PersonTriangulation

__all__ = ["FuseSummary", "summarise", "write_report", "LANDMARK_SEGMENTS"]

# segments between triangulated landmarks whose length is a bone's
LANDMARK_SEGMENTS = {
    f"{s}_{a}": (f"{s}_{x}", f"{s}_{y}")
    for s in ("left", "right")
    for a, (x, y) in {
        "upper_arm": ("shoulder", "elbow"),
        "forearm": ("elbow", "wrist"),
        "thigh": ("hip", "knee"),
        "shin": ("knee", "ankle"),
    }.items()
}


# a rotation the fitted bodies had to correct by more than this (degrees) says the camera was
# moved or the calibration is off: on the lab cam03 0.45-0.8 (17 px against both people), the
# other three 0.05-0.3
RECALIBRATE_DEG = 0.4


def _stats(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"mean_m": None, "cv": None, "robust_cv": None, "frames": 0}
    med = float(np.median(x))
    return {
        "mean_m": float(x.mean()),
        "cv": float(x.std() / x.mean()),
        "robust_cv": float(1.4826 * np.median(np.abs(x - med)) / med),
        "frames": int(len(x)),
    }


@dataclass
class FuseSummary:
    people: list[dict] = field(default_factory=list)
    reprojection_px: dict = field(default_factory=dict)  # camera -> landmark -> median
    median_reprojection_px: float = float("nan")  # every reading of every view
    # only the readings the triangulation took as showing the landmark (its inlier views; as
    # Pose2Sim reports its reprojection error): what the fit explains, without the misreadings
    median_reprojection_used_px: float | None = None
    gap_filled_share: float = float("nan")
    frames: int = 0
    truth: dict | None = None
    camera_corrections_deg: dict = field(default_factory=dict)  # gst.fuse.rig, per camera
    # (view, limb group) pairs the fitted body said were read mirrored, exchanged and refitted
    exchanged_view_groups: int = 0

    def headline(self) -> str:
        """One line for the log: people, reprojection, gap share and, on synthetic scenes, the
        error against the truth."""
        truth = (
            f"; MPJPE {self.truth['mpjpe_mm']:.1f} mm, PA-MPJPE {self.truth['pa_mpjpe_mm']:.1f} mm"
            f", truth person-frames missed {_missed(self.truth)}"
            if self.truth
            else ""
        )
        reprojection = self.median_reprojection_px or float("nan")
        used = self.median_reprojection_used_px or float("nan")
        return (
            f"{len(self.people)} people, median reprojection {reprojection:.1f} px "
            f"({used:.1f} px in the views used), "
            f"gap-filled {100 * (self.gap_filled_share or 0.0):.1f}%{truth}"
        )

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _used_readings(fit: PersonFit, tri: PersonTriangulation | None) -> np.ndarray:
    """The fit's reprojection errors (px) of the readings the triangulation used (1-D)."""
    if tri is None:
        return np.zeros(0)
    used = np.transpose(tri.used, (0, 2, 1)) & np.isfinite(fit.reprojection)  # (T, C, 33)
    return fit.reprojection[used]


def summarise(
    fits: list[PersonFit],
    tris: list[PersonTriangulation | None],
    evidence: list[JointEvidence],
    camera_names: list[str],
    n_frames: int,
    truth: dict | None = None,
    limb_lengths: list[dict[str, np.ndarray]] | None = None,
) -> FuseSummary:
    """`limb_lengths`: per person, gst.fuse.consistency.per_frame_limb_lengths."""
    s = FuseSummary(frames=n_frames, truth=truth)
    allr = (
        np.concatenate([f.reprojection.reshape(-1, *f.reprojection.shape[1:]) for f in fits])
        if fits
        else np.zeros((0, len(camera_names), 33))
    )
    # a camera and landmark without a reading: NaN in the report (numpy warns "All-NaN slice",
    # which errstate does not silence, in the log of most runs)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for c, cam in enumerate(camera_names):
            med = np.nanmedian(allr[:, c], axis=0) if len(allr) else np.full(33, np.nan)
            s.reprojection_px[cam] = {
                n: (None if not np.isfinite(v) else round(float(v), 2))
                for n, v in zip(BLAZEPOSE_NAMES, med, strict=True)
            }
        s.median_reprojection_px = float(np.nanmedian(allr)) if np.isfinite(allr).any() else None
    used = [_used_readings(f, t) for f, t in zip(fits, tris, strict=True)]
    every_used = np.concatenate(used) if used else np.zeros(0)
    s.median_reprojection_used_px = float(np.median(every_used)) if len(every_used) else None
    gaps = [ev.gap_filled[:, ev.has_landmarks] for ev in evidence]
    s.gap_filled_share = float(np.concatenate(gaps).mean()) if gaps else None
    limbs_all = limb_lengths if limb_lengths is not None else [None] * len(fits)
    for fit, tri, ev, limbs, mine in zip(fits, tris, evidence, limbs_all, used, strict=True):
        frame_fit = {k: _stats(v) for k, v in limbs.items()} if limbs is not None else {}
        bones = {}
        for j, p in enumerate(SMPL_PARENTS):
            if p >= 0:
                length = np.linalg.norm(fit.joints[:, j] - fit.joints[:, p], axis=-1)
                bones[f"{SMPL_JOINT_NAMES[p]}-{SMPL_JOINT_NAMES[j]}"] = _stats(length)
        segs = {}
        if tri is not None:
            for name, (a, b) in LANDMARK_SEGMENTS.items():
                ia, ib = BLAZEPOSE_NAMES.index(a), BLAZEPOSE_NAMES.index(b)
                length = np.linalg.norm(tri.points[:, ia] - tri.points[:, ib], axis=-1)
                segs[name] = _stats(length)
        with np.errstate(all="ignore"):
            reproj = (
                float(np.nanmedian(fit.reprojection))
                if np.isfinite(fit.reprojection).any()
                else None
            )
        s.people.append(
            {
                "person_id": fit.person_id,
                "frames": int(len(fit.frames)),
                "first_frame": int(fit.frames[0]) if len(fit.frames) else None,
                "last_frame": int(fit.frames[-1]) if len(fit.frames) else None,
                "observed_frames": int(fit.observed.sum()),
                "static_frames": int(fit.static.sum()),
                "single_view": fit.single_view,
                "median_reprojection_px": reproj,
                "median_reprojection_used_px": float(np.median(mine)) if len(mine) else None,
                "gap_filled_share": float(ev.gap_filled[:, ev.has_landmarks].mean()),
                "cauchy_sigma_px": fit.sigma_px,
                "betas": [round(float(b), 4) for b in fit.betas],
                "fit_bone_lengths": bones,
                "triangulated_segments": segs,
                "per_frame_fit_segments": frame_fit,
                "max_per_frame_fit_cv": max(
                    (v["cv"] for v in frame_fit.values() if v["cv"] is not None), default=None
                ),
                "max_fit_bone_cv": max((v["cv"] or 0.0) for v in bones.values()) if bones else None,
                "max_triangulated_segment_cv": max(
                    (v["cv"] for v in segs.values() if v["cv"] is not None), default=None
                ),
            }
        )
    return s


def write_report(
    summary: FuseSummary,
    out_dir: Path,
    fits: list[PersonFit],
    tris: list[PersonTriangulation | None],
    limb_lengths: list[dict[str, np.ndarray]] | None = None,
) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = (
        json.dumps(
            finite_json(summary.as_dict()), indent=1, sort_keys=True, default=float, allow_nan=False
        )
        + "\n"
    )
    atomic_write(out_dir / "summary.json", lambda t: Path(t).write_text(doc))
    lines = ["# Fusion report", ""]
    lines.append(
        f"{len(summary.people)} people over {summary.frames} frames. Median reprojection error "
        f"of the fitted markers: {_fmt(summary.median_reprojection_px)} px (full image) over "
        f"every reading, {_fmt(summary.median_reprojection_used_px)} px over the readings the "
        "triangulation used (its inlier views, as Pose2Sim reports it). "
        f"Share of observable joint-frames filled by the fit (< 2 views): "
        f"{_fmt(100 * summary.gap_filled_share if summary.gap_filled_share is not None else None)}"
        " %."
    )
    if summary.camera_corrections_deg:
        corrections = summary.camera_corrections_deg
        corr = ", ".join(f"{c} {v:.2f}" for c, v in corrections.items())
        redo = [c for c, v in corrections.items() if v > RECALIBRATE_DEG]
        verdict = (
            f"Worth calibrating again: {', '.join(redo)} (more than {RECALIBRATE_DEG} degrees)."
            if redo
            else f"None more than {RECALIBRATE_DEG} degrees: the calibration holds."
        )
        lines += [
            "",
            f"Camera rotations corrected from the fitted bodies (degrees, all rounds together): "
            f"{corr}. {verdict}",
        ]
    if summary.exchanged_view_groups:
        lines += [
            "",
            f"Limb groups of single views read mirrored (left for right) and exchanged after the "
            f"fit: {summary.exchanged_view_groups} (gst.fuse.consensus.exchanges_against_body).",
        ]
    if summary.truth:
        t = summary.truth
        lines += [
            "",
            "## Against the synthetic truth",
            "",
            "| MPJPE mm | PA-MPJPE mm | vertex error mm | person-frames | unmatched | truth "
            "missed |",
            "| --- | --- | --- | --- | --- | --- |",
            f"| {_fmt(t['mpjpe_mm'])} | {_fmt(t['pa_mpjpe_mm'])} | {_fmt(t['vertex_error_mm'])} "
            f"| {t['matched']} | {t['unmatched']} | {_missed(t)} |",
            "",
            "Unmatched: fused person-frames with no truth body within 0.5 m. Truth missed: truth "
            "person-frames at least 30 % visible in some camera that no fused body was paired "
            "with (the errors above leave them out).",
        ]
    lines += ["", "## People", "", "| id | frames | first-last | observed | static | single view "
              "| reprojection px (all / used) | gap-filled % | max triangulated segment CV % |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for p in summary.people:
        cv = p["max_triangulated_segment_cv"]
        lines.append(
            f"| {p['person_id']} | {p['frames']} | {p['first_frame']}-{p['last_frame']} | "
            f"{p['observed_frames']} | {p['static_frames']} | {p['single_view']} | "
            f"{_fmt(p['median_reprojection_px'])} / {_fmt(p['median_reprojection_used_px'])} | "
            f"{_fmt(100 * p['gap_filled_share'])} | "
            f"{_fmt(None if cv is None else 100 * cv)} |"
        )
    names = list(LANDMARK_SEGMENTS)
    for key, title in (
        ("per_frame_fit_segments", "Limb lengths, each frame fitted with its own shape"),
        ("triangulated_segments", "Limb lengths between triangulated landmarks"),
    ):
        lines += ["", f"## {title} (mean m / CV % / robust CV %)", ""]
        lines += ["| id | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
        for p in summary.people:
            seg = p[key]
            cells = [
                f"{_fmt(seg[n]['mean_m'], 3)} / {_pct(seg[n]['cv'])} / {_pct(seg[n]['robust_cv'])}"
                if n in seg
                else "-"
                for n in names
            ]
            lines.append(f"| {p['person_id']} | " + " | ".join(cells) + " |")
    lines += ["", "## Median reprojection error per camera and landmark (px)", ""]
    short = [n for n in BLAZEPOSE_NAMES if "eye" not in n and "mouth" not in n]
    lines += ["| camera | " + " | ".join(short) + " |", "| --- |" + " --- |" * len(short)]
    for cam, per in summary.reprojection_px.items():
        lines.append(f"| {cam} | " + " | ".join(_fmt(per[n]) for n in short) + " |")
    lines += ["", "![segment lengths](bone_lengths.png)", ""]
    text = "\n".join(lines)
    atomic_write(out_dir / "report.md", lambda t: Path(t).write_text(text))
    _plot(out_dir / "bone_lengths.png", fits, tris, limb_lengths)


def _pct(v) -> str:
    return _fmt(None if v is None else 100 * v)


def _missed(t: dict) -> str:
    """`truth_missed` of `truth_expected` with its share, or "-" where not counted."""
    missed, expected = t.get("truth_missed"), t.get("truth_expected")
    if missed is None or not expected:
        return "-"
    return f"{missed} of {expected} ({100 * missed / expected:.1f} %)"


def _fmt(v, digits: int = 1) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def _plot(
    path: Path,
    fits: list[PersonFit],
    tris: list[PersonTriangulation | None],
    limbs: list[dict[str, np.ndarray]] | None = None,
) -> None:
    """Per person: limb lengths over time, each frame fitted with its own shape (solid) and
    between triangulated landmarks (dotted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(fits))
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.6 * n), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    # one colour per limb: the fitted body is symmetric (its left and right lengths are one
    # line, drawn once), the triangulated left dotted and right dash-dotted
    kinds = list(dict.fromkeys(name.split("_", 1)[1] for name in LANDMARK_SEGMENTS))
    for k, (ax, fit, tri) in enumerate(zip(axes[:, 0], fits, tris, strict=False)):
        for name, (a, b) in LANDMARK_SEGMENTS.items():
            side, kind = name.split("_", 1)
            col = colours[kinds.index(kind) % len(colours)]
            if limbs is not None and name in limbs[k] and side == "left":
                ax.plot(fit.frames, limbs[k][name], lw=1.4, color=col, label=kind.replace("_", " "))
            if tri is not None:
                ia, ib = BLAZEPOSE_NAMES.index(a), BLAZEPOSE_NAMES.index(b)
                seg = np.linalg.norm(tri.points[:, ia] - tri.points[:, ib], axis=-1)
                ax.plot(fit.frames, seg, lw=0.7, ls=":" if side == "left" else "-.", color=col)
        ax.set_ylim(0.1, 0.6)
        ax.set_title(f"person {fit.person_id}: limb lengths (solid: per-frame fit, left and "
                     "right alike; triangulated: left dotted, right dash-dotted; clipped at "
                     "0.6 m)", fontsize=8)  # fmt: skip
        ax.set_xlabel("frame")
        ax.set_ylabel("m")
    if fits:  # nobody fused: an empty figure, no legend to draw; beside the plot, not on it
        axes[0, 0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    atomic_write(path, lambda t: fig.savefig(t, format="png", dpi=90))
    plt.close(fig)
