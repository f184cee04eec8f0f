"""Error statistics of 2D landmark detections against the truth, one function for real and
simulated detections alike (so the noise model is checked with the same ruler it was fitted on).

The 12 limb landmarks of BlazePose (shoulders, elbows, wrists, hips, knees, ankles) are compared
with their body joints (`gst.train.keypoints.BODY_FROM_BLAZEPOSE`). Distances are in units of
the crop size (a crop is the person's square box with margin, so this is a body-scale
normalisation; x 256 gives pixels of a 256 px crop). A detection counts as dropped when its
confidence (visibility x presence) is below 0.5. A left/right pair counts as swapped when
assigning each detection to the other side's truth is cheaper than the direct assignment, among
pairs whose true joints lie at least `MIN_PAIR_SEPARATION` apart (closer pairs cannot be told
apart); a crop is flipped when most of its countable pairs are swapped.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# (landmark, body joint) for the 12 limb landmarks, left/right alternating
LIMB_LANDMARKS: tuple[tuple[int, int], ...] = (
    (11, 16),  # left shoulder
    (12, 17),
    (13, 18),  # elbows
    (14, 19),
    (15, 20),  # wrists
    (16, 21),
    (23, 1),  # hips
    (24, 2),
    (25, 4),  # knees
    (26, 5),
    (27, 7),  # ankles
    (28, 8),
)
LIMB_NAMES = (
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
)
# Pairs as indices into LIMB_LANDMARKS (left, right)
LR_PAIRS = tuple((2 * k, 2 * k + 1) for k in range(6))
DROP_CONFIDENCE = 0.5
OUTLIER = 0.1  # crop sizes: farther than this (and not a swap) is a gross error
MIN_PAIR_SEPARATION = 0.05
CONF_BINS = np.linspace(0.0, 1.0, 11)


@dataclass(frozen=True)
class DetectionStats:
    """Per limb landmark (12, in LIMB_LANDMARKS order) unless said otherwise. Errors in crop
    sizes; `*_visible` over joints the truth marks visible, `*_occluded` over the others."""

    n_crops: int
    err_median_visible: np.ndarray  # (12,)
    err_mean_visible: np.ndarray
    err_p90_visible: np.ndarray
    err_median_occluded: np.ndarray
    offset_mean: np.ndarray  # (12, 2) mean (detected - true) of visible inliers, u and v
    offset_sd: np.ndarray  # (12, 2) its standard deviation per axis
    outlier_visible: np.ndarray  # (12,) error > OUTLIER, not swapped, visible
    outlier_occluded: np.ndarray
    drop_visible: np.ndarray  # (12,) confidence < 0.5 where the truth is visible
    drop_occluded: np.ndarray  # (12,) where occluded
    occluded_rate: np.ndarray  # (12,) of the truth
    conf_hist_visible: np.ndarray  # (10,) confidence histogram of all limb landmarks, density
    conf_hist_occluded: np.ndarray  # (10,)
    swap_rate: np.ndarray  # (6,) per left/right pair (shoulders .. ankles)
    flip_rate: float  # crops with most pairs swapped
    presence_p05: float  # 5th percentile of the presence score

    def to_json(self) -> dict:
        return {
            k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()
        }

    @classmethod
    def from_json(cls, d: dict) -> DetectionStats:
        return cls(**{k: (np.asarray(v) if isinstance(v, list) else v) for k, v in d.items()})


def pair_swaps(
    det: np.ndarray, truth: np.ndarray, in_image: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """det, truth (N, 12, 2) in crop sizes; in_image (N, 12) bool.
    Returns swapped (N, 6) bool and countable (N, 6) bool per left/right pair."""
    swapped = np.zeros((len(det), len(LR_PAIRS)), bool)
    countable = np.zeros_like(swapped)
    for k, (a, b) in enumerate(LR_PAIRS):
        direct = np.linalg.norm(det[:, a] - truth[:, a], axis=1) + np.linalg.norm(
            det[:, b] - truth[:, b], axis=1
        )
        cross = np.linalg.norm(det[:, a] - truth[:, b], axis=1) + np.linalg.norm(
            det[:, b] - truth[:, a], axis=1
        )
        sep = np.linalg.norm(truth[:, a] - truth[:, b], axis=1)
        countable[:, k] = in_image[:, a] & in_image[:, b] & (sep >= MIN_PAIR_SEPARATION)
        swapped[:, k] = countable[:, k] & (cross < direct)
    return swapped, countable


def _hist(x: np.ndarray) -> np.ndarray:
    h, _ = np.histogram(np.clip(x, 0, 1), bins=CONF_BINS)
    return h / max(1, h.sum())


def _rate(flag: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Per-column mean of `flag` over the rows where `where` is set (NaN for none)."""
    n = where.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (flag & where).sum(0) / np.maximum(n, 1), np.nan)


def detection_stats(
    landmarks: np.ndarray,
    presence: np.ndarray,
    joints2d: np.ndarray,
    visible: np.ndarray,
    crop_size: float,
) -> DetectionStats:
    """landmarks (N, 33, 3) u, v crop px + visibility; presence (N,); joints2d (N, 24, 2) crop
    px; visible (N, 24) bool (the truth's visibility)."""
    lm_idx = [lm for lm, _ in LIMB_LANDMARKS]
    j_idx = [j for _, j in LIMB_LANDMARKS]
    det = landmarks[:, lm_idx, :2] / crop_size
    conf = landmarks[:, lm_idx, 2] * presence[:, None]
    tru = joints2d[:, j_idx] / crop_size
    vis = visible[:, j_idx].astype(bool)
    occ = ~vis
    in_image = ((tru >= 0) & (tru <= 1)).all(-1)
    swapped, countable = pair_swaps(det, tru, in_image)
    swapped_lm = np.zeros_like(vis)
    for k, (a, b) in enumerate(LR_PAIRS):
        swapped_lm[:, a] |= swapped[:, k]
        swapped_lm[:, b] |= swapped[:, k]
    diff = det - tru
    err = np.linalg.norm(diff, axis=-1)
    inlier = vis & ~swapped_lm & (err <= OUTLIER)

    def per_col(fn, mask):
        return np.array([fn(err[mask[:, k], k]) if mask[:, k].any() else np.nan for k in range(12)])

    def p90(x):
        return np.percentile(x, 90)

    off_mean = np.stack([diff[inlier[:, k], k].mean(0) for k in range(12)])
    off_sd = np.stack([diff[inlier[:, k], k].std(0) for k in range(12)])
    n_count = countable.sum(1)
    flipped = (n_count > 0) & (swapped.sum(1) * 2 > n_count)
    return DetectionStats(
        n_crops=int(len(landmarks)),
        err_median_visible=per_col(np.median, vis),
        err_mean_visible=per_col(np.mean, vis),
        err_p90_visible=per_col(p90, vis),
        err_median_occluded=per_col(np.median, occ),
        offset_mean=off_mean,
        offset_sd=off_sd,
        outlier_visible=_rate((err > OUTLIER) & ~swapped_lm, vis),
        outlier_occluded=_rate((err > OUTLIER) & ~swapped_lm, occ),
        drop_visible=_rate(conf < DROP_CONFIDENCE, vis),
        drop_occluded=_rate(conf < DROP_CONFIDENCE, occ),
        occluded_rate=occ.mean(0),
        conf_hist_visible=_hist(conf[vis]),
        conf_hist_occluded=_hist(conf[occ]),
        swap_rate=_rate(swapped, countable),
        flip_rate=float(flipped.mean()),
        presence_p05=float(np.percentile(presence, 5)),
    )
