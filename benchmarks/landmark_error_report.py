"""BlazePose's error on rendered synthetic crops against the truth (docs/landmark_prior.md).

Reads the landmark worlds (`python -m gst.lift.dataset`), prints per-landmark 2D statistics
(`gst.lift.errors.detection_stats`), and the accuracy of BlazePose's world landmarks against the
true joints in the crop's camera frame (root-aligned at the mid-hips, and after a similarity
Procrustes), with the mean-pose baseline beside it.

    python benchmarks/landmark_error_report.py --worlds /work/data/landmark_worlds
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from gst.lift.dataset import load_worlds  # noqa: E402
from gst.lift.errors import LIMB_LANDMARKS, LIMB_NAMES, LR_PAIRS, detection_stats  # noqa: E402
from gst.lift.noise import POSE_KINDS, pose_kind  # noqa: E402
from gst.metrics.pose import pa_mpjpe, similarity_procrustes  # noqa: E402


def _cat(worlds, key):
    return np.concatenate([getattr(w, key) for w in worlds])


def world_landmark_accuracy(worlds, min_conf: float = 0.0) -> dict:
    """MPJPE (mm) of the 12 limb world landmarks against the true joints, camera frame."""
    lm_idx = [lm for lm, _ in LIMB_LANDMARKS]
    j_idx = [j for _, j in LIMB_LANDMARKS]
    R, t = _cat(worlds, "R"), _cat(worlds, "t")
    jc = np.einsum("nij,nkj->nki", R, _cat(worlds, "joints_world")) + t[:, None]
    truth = jc[:, j_idx]
    truth = truth - truth[:, 6:8].mean(1, keepdims=True)  # mid-hips
    wl = _cat(worlds, "world_landmarks")[:, lm_idx].astype(np.float64)
    pred = wl - wl[:, 6:8].mean(1, keepdims=True)
    conf = _cat(worlds, "landmarks")[:, lm_idx, 2] * _cat(worlds, "presence")[:, None]
    keep = conf.min(1) >= min_conf
    pred, truth = pred[keep], truth[keep]
    p, g = torch.from_numpy(pred), torch.from_numpy(truth)
    root = 1000 * np.linalg.norm(pred - truth, axis=-1).mean()
    pa = 1000 * float(pa_mpjpe(p, g).mean())
    sim = similarity_procrustes(p, g)
    # rotation of the best alignment: how far the world landmarks' axes are from the camera's
    ang = np.degrees(
        np.arccos(np.clip((np.trace(sim.rotation.numpy(), axis1=1, axis2=2) - 1) / 2, -1, 1))
    )
    # baseline: the mean root-aligned pose of all crops (camera frame), same metric
    mean_pose = truth.mean(0, keepdims=True)
    base = 1000 * np.linalg.norm(mean_pose - truth, axis=-1).mean()
    base_pa = 1000 * float(
        pa_mpjpe(torch.from_numpy(np.repeat(mean_pose, len(truth), 0)), g).mean()
    )
    # scale: ratio of the summed limb lengths
    bones = [(0, 2), (2, 4), (1, 3), (3, 5), (6, 8), (8, 10), (7, 9), (9, 11)]

    def length(x):
        return sum(np.linalg.norm(x[:, a] - x[:, b], axis=-1) for a, b in bones)

    return {
        "crops": int(keep.sum()),
        "mpjpe_root_mm": float(root),
        "pa_mpjpe_mm": pa,
        "per_joint_root_mm": (1000 * np.linalg.norm(pred - truth, axis=-1).mean(0)).tolist(),
        "alignment_rotation_deg_median": float(np.median(ang)),
        "alignment_scale_median": float(np.median(sim.scale.numpy())),
        "limb_length_ratio_median": float(np.median(length(pred) / length(truth))),
        "mean_pose_root_mm": float(base),
        "mean_pose_pa_mm": base_pa,
        "depth_sign_agreement": float(
            np.mean(
                np.sign(pred[..., 2] - pred[..., 2].mean(1, keepdims=True))
                == np.sign(truth[..., 2] - truth[..., 2].mean(1, keepdims=True))
            )
        ),
    }


def _table(s, title: str) -> None:
    print(f"\n### {title}: {s.n_crops} crops; errors in % of the crop size\n")
    print(
        "| landmark | median vis | mean vis | p90 vis | median occ | offset u, v | sd u, v | "
        "gross vis / occ | dropped vis / occ | occluded |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for k, name in enumerate(LIMB_NAMES):
        print(
            f"| {name} | {100 * s.err_median_visible[k]:.1f} | {100 * s.err_mean_visible[k]:.1f} "
            f"| {100 * s.err_p90_visible[k]:.1f} | {100 * s.err_median_occluded[k]:.1f} "
            f"| {100 * s.offset_mean[k, 0]:+.1f}, {100 * s.offset_mean[k, 1]:+.1f} "
            f"| {100 * s.offset_sd[k, 0]:.1f}, {100 * s.offset_sd[k, 1]:.1f} "
            f"| {100 * s.outlier_visible[k]:.1f} / {100 * s.outlier_occluded[k]:.1f} "
            f"| {100 * s.drop_visible[k]:.1f} / {100 * s.drop_occluded[k]:.1f} "
            f"| {100 * s.occluded_rate[k]:.1f} |"
        )
    pairs = [LIMB_NAMES[a][2:] for a, _ in LR_PAIRS]
    swaps = ", ".join(f"{p} {100 * r:.1f}" for p, r in zip(pairs, s.swap_rate, strict=True))
    print(f"\nleft/right swaps (% of countable pairs): {swaps}")
    print(f"whole-body flips: {100 * s.flip_rate:.1f}% of crops; presence p05 {s.presence_p05:.3f}")
    print("confidence histogram (% per 0.1 bin), visible:", np.round(100 * s.conf_hist_visible, 1))
    print(
        "                                      occluded:", np.round(100 * s.conf_hist_occluded, 1)
    )


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--worlds", type=Path, required=True)
    args = ap.parse_args()
    worlds = load_worlds(args.worlds)
    kind_all = pose_kind(_cat(worlds, "motion"))
    for kind in POSE_KINDS:
        sel = kind_all == kind
        arrays = [_cat(worlds, k)[sel] for k in ("landmarks", "presence", "joints2d", "visible")]
        _table(detection_stats(*arrays, worlds[0].crop_size), f"{kind} poses")
    print("\nper world (median visible error over the landmarks, % of crop; swaps; flips):")
    for w in worlds:
        sk = detection_stats(w.landmarks, w.presence, w.joints2d, w.visible, w.crop_size)
        print(
            f"  {w.seed} {w.rig_kind} {pose_kind(w.motion)[0]}: "
            f"{100 * np.median(sk.err_median_visible):.2f}%, "
            f"swaps {100 * np.mean(sk.swap_rate):.1f}%,"
            f" flips {100 * sk.flip_rate:.1f}%, "
            f"dropped (visible) {100 * np.mean(sk.drop_visible):.1f}%"
        )
    for kind in POSE_KINDS:
        sub = [w for w in worlds if pose_kind(w.motion)[0] == kind]
        for min_conf in (0.0, 0.5):
            acc = world_landmark_accuracy(sub, min_conf)
            print(f"\nworld landmarks, {kind} poses (every limb confidence >= {min_conf}):")
            for k, v in acc.items():
                print(f"  {k}: {np.round(v, 1) if isinstance(v, list) else round(v, 3)}")


if __name__ == "__main__":
    main()
