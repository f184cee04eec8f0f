"""Aggregate per-crop and per-view records into the evaluation summary (docs/evaluate.md).

Pose errors are reported in millimetres; image scores as they are (PSNR in dB). Means skip NaN
(e.g. a body box outside a view) and every group says how many records it averaged.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from gst.eval.evaluator import PoseRecords, ViewRecords

__all__ = [
    "JOINT_GROUPS",
    "PoseSummary",
    "ViewSummary",
    "joint_group_indices",
    "pose_summary",
    "view_summary",
]

# Body parts as groups of SMPL-layout joints (names as in the scene's truth).
JOINT_GROUPS: dict[str, tuple[str, ...]] = {
    "torso": ("pelvis", "spine1", "spine2", "spine3"),
    "head": ("neck", "head"),
    "arms": (
        "left_collar",
        "right_collar",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
    ),
    "hands": ("left_wrist", "right_wrist", "left_hand", "right_hand"),
    "legs": ("left_hip", "right_hip", "left_knee", "right_knee"),
    "feet": ("left_ankle", "right_ankle", "left_foot", "right_foot"),
}


def joint_group_indices(joint_names: tuple[str, ...] | list[str]) -> dict[str, list[int]]:
    """Joint indices of every body part in JOINT_GROUPS; raises if a joint name is unknown."""
    names = list(joint_names)
    out = {}
    for part, members in JOINT_GROUPS.items():
        missing = [m for m in members if m not in names]
        if missing:
            raise ValueError(f"joint names {names} lack {missing} (body part '{part}')")
        out[part] = [names.index(m) for m in members]
    return out


def _mean(x: np.ndarray) -> float | None:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else None


def _median(x: np.ndarray) -> float | None:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def _pose_block(rec: PoseRecords, sel: np.ndarray) -> dict:
    block = {
        "n": int(sel.sum()),
        # records whose error is NaN or infinite (a diverged prediction): left out of the means
        "n_not_finite": int((~np.isfinite(rec.mpjpe[sel]) | ~np.isfinite(rec.pa_mpjpe[sel])).sum()),
        "mpjpe_mm": _mean(1000 * rec.mpjpe[sel]),
        "pa_mpjpe_mm": _mean(1000 * rec.pa_mpjpe[sel]),
        "mpjpe_median_mm": _median(1000 * rec.mpjpe[sel]),
    }
    if rec.pve is not None:
        block.update(pve_mm=_mean(1000 * rec.pve[sel]), pa_pve_mm=_mean(1000 * rec.pa_pve[sel]))
    if rec.mirrored is not None:  # how much of the error is the detector's left/right reading
        kept = sel & ~rec.mirrored
        block.update(
            mirrored_landmarks=int((sel & rec.mirrored).sum()),
            mpjpe_mm_not_mirrored=_mean(1000 * rec.mpjpe[kept]),
        )
    return block


@dataclass(frozen=True)
class PoseSummary:
    """Pose errors (mm): `overall`, then by camera, by motion, by body part and by joint (each
    table keyed by its name). A block is metric name -> value ("n", "n_not_finite" (records
    whose error is not finite, left out of the means), "mpjpe_mm", "pa_mpjpe_mm",
    "mpjpe_median_mm", and "pve_mm", "pa_pve_mm" when vertices were scored; with landmark input,
    "mirrored_landmarks" (crops whose landmarks are left/right mirrored against the reference,
    gst.metrics.flips) and "mpjpe_mm_not_mirrored"; None where nothing finite was averaged), as
    written to summary.json."""

    overall: dict
    per_camera: dict[str, dict]
    per_motion: dict[str, dict]
    per_part: dict[str, dict]
    per_joint: dict[str, dict]

    def to_dict(self) -> dict:
        """The summary.json layout (the fields in order)."""
        return asdict(self)


@dataclass(frozen=True)
class ViewSummary:
    """Novel-view scores: `heldout` (the headline: targets in cameras never trained on),
    `trained_views` (other training cameras than the input's), then by target camera (with its
    "heldout" flag) and by motion (held-out targets). A block is metric name -> value ("n",
    VIEW_KEYS, and "n_<metric>" where fewer records were finite), as written to summary.json."""

    heldout: dict
    trained_views: dict
    per_target_camera: dict[str, dict]
    per_motion: dict[str, dict]

    def to_dict(self) -> dict:
        """The summary.json layout (the fields in order)."""
        return asdict(self)


def pose_summary(
    rec: PoseRecords,
    camera_names: list[str],
    motions: np.ndarray,
    joint_names: tuple[str, ...] | list[str],
) -> PoseSummary:
    """Pose errors (mm) overall, per camera, motion, body part and joint. `motions` (N,) is the
    motion label of each record."""
    every = np.ones(len(rec.rows), dtype=bool)
    motions = np.asarray(motions, dtype=object)
    per_part = {}
    for part, idx in joint_group_indices(joint_names).items():
        per_part[part] = {
            "mpjpe_mm": _mean(1000 * rec.joint_error[:, idx].mean(1)),
            "pa_mpjpe_mm": _mean(1000 * rec.joint_error_pa[:, idx].mean(1)),
        }
    return PoseSummary(
        overall=_pose_block(rec, every),
        per_camera={
            camera_names[c]: _pose_block(rec, rec.camera == c)
            for c in sorted(set(rec.camera.tolist()))
        },
        per_motion={str(m): _pose_block(rec, motions == m) for m in sorted(set(motions.tolist()))},
        per_part=per_part,
        per_joint={
            name: {
                "mpjpe_mm": _mean(1000 * rec.joint_error[:, j]),
                "pa_mpjpe_mm": _mean(1000 * rec.joint_error_pa[:, j]),
            }
            for j, name in enumerate(joint_names)
        },
    )


VIEW_KEYS = (
    "psnr",
    "ssim",
    "lpips",
    "silhouette_iou",
    "box_psnr",
    "box_ssim",
    "box_lpips",
    "psnr_unoccluded",
    "silhouette_iou_unoccluded",
)


def _view_block(rec: ViewRecords, sel: np.ndarray) -> dict:
    """ "n" the records selected; "n_<metric>" where fewer of them were finite (the SHERF box's
    metrics are NaN where the box is not visible): the number its mean is over."""
    block: dict = {"n": int(sel.sum())}
    for k in VIEW_KEYS:
        values = np.asarray(getattr(rec, k)[sel], dtype=np.float64)
        block[k] = _mean(values)
        finite = int(np.isfinite(values).sum())
        if finite < block["n"]:
            block[f"n_{k}"] = finite
    return block


def view_summary(rec: ViewRecords, camera_names: list[str], motions: np.ndarray) -> ViewSummary:
    """Novel-view scores: held-out targets, trained views, per target camera, per motion.
    `motions` (P,) is the motion label of each pair. "heldout" is the headline: targets in
    cameras never trained on; "trained_views": other training cameras than the input's."""
    motions = np.asarray(motions, dtype=object)
    held = rec.heldout.astype(bool)
    return ViewSummary(
        heldout=_view_block(rec, held),
        trained_views=_view_block(rec, ~held),
        per_target_camera={
            camera_names[c]: {
                **_view_block(rec, rec.camera == c),
                "heldout": bool(held[rec.camera == c].any()),
            }
            for c in sorted(set(rec.camera.tolist()))
        },
        per_motion={
            str(m): _view_block(rec, held & (motions == m)) for m in sorted(set(motions.tolist()))
        },
    )
