"""Error statistics of 2D landmark detections against the truth, one function for real and
simulated detections alike (so the noise model is checked with the same ruler it was fitted on).

Two landmark sets (`LandmarkSet`):

- `LIMBS`: the 12 limb landmarks of BlazePose (shoulders, elbows, wrists, hips, knees, ankles)
  against their body joints (`gst.train.keypoints.BODY_FROM_BLAZEPOSE`);
- `ALL`: all 33 landmarks against the virtual markers (`gst.body.markers.MarkerModel`: where on
  the body each landmark lies), projected into the crop (`gst.lift.references`).

Distances are in units of the crop size (a crop is the person's square box with margin, so this
is a body-scale normalisation; x 256 gives pixels of a 256 px crop). A detection counts as
dropped when its confidence (visibility x presence) is below 0.5. A left/right pair counts as
swapped when assigning each detection to the other side's truth is cheaper than the direct
assignment, among pairs whose true points lie at least `MIN_PAIR_SEPARATION` apart (closer pairs
cannot be told apart); a crop is flipped when most of its countable pairs are swapped.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from gst.body.markers import BLAZEPOSE_NAMES

DROP_CONFIDENCE = 0.5
OUTLIER = 0.1  # crop sizes: farther than this (and not a swap) is a gross error
MIN_PAIR_SEPARATION = 0.05
CONF_BINS = np.linspace(0.0, 1.0, 11)


@dataclass(frozen=True)
class LandmarkSet:
    """A set of BlazePose landmarks and how their errors are modelled.

    ids: BlazePose indices; pairs: left/right pairs as positions in `ids`; bones: per landmark
    the (from, to) SMPL joints whose image direction frames its systematic offset; swap_group:
    per pair, the group whose swap it follows (hand landmarks swap with the wrists); joints:
    per landmark the body joint that is its reference (LIMBS) or None (markers)."""

    name: str
    ids: tuple[int, ...]
    pairs: tuple[tuple[int, int], ...]
    bones: tuple[tuple[int, int], ...]
    swap_group: tuple[int, ...]
    joints: tuple[int, ...] | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(BLAZEPOSE_NAMES[i] for i in self.ids)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def n_groups(self) -> int:
        return max(self.swap_group) + 1


_LIMB_IDS = (11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
LIMBS = LandmarkSet(
    name="limbs",
    ids=_LIMB_IDS,
    pairs=tuple((2 * k, 2 * k + 1) for k in range(6)),
    bones=(
        (16, 18),  # shoulders: upper arm
        (17, 19),
        (16, 18),  # elbows: upper arm
        (17, 19),
        (18, 20),  # wrists: forearm
        (19, 21),
        (1, 4),  # hips: thigh
        (2, 5),
        (1, 4),  # knees: thigh
        (2, 5),
        (4, 7),  # ankles: shin
        (5, 8),
    ),
    swap_group=(0, 1, 2, 3, 4, 5),
    joints=(16, 17, 18, 19, 20, 21, 1, 2, 4, 5, 7, 8),
)

# All 33, in MediaPipe order. Bones: the face follows neck -> head, hand landmarks the forearm,
# heels the shin, foot tips ankle -> foot.
_HEAD, _FACE = (12, 15), (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10)
_ALL_BONES = {i: _HEAD for i in _FACE}
_ALL_BONES.update({i: LIMBS.bones[k] for k, i in enumerate(_LIMB_IDS)})
_ALL_BONES.update({17: (18, 20), 19: (18, 20), 21: (18, 20), 18: (19, 21), 20: (19, 21)})
_ALL_BONES.update({22: (19, 21), 29: (4, 7), 30: (5, 8), 31: (7, 10), 32: (8, 11)})
_ALL_PAIRS = (
    (1, 4), (2, 5), (3, 6), (7, 8), (9, 10),  # face: eyes, ears, mouth
    (11, 12), (13, 14), (15, 16), (17, 18), (19, 20), (21, 22),  # arms and hands
    (23, 24), (25, 26), (27, 28), (29, 30), (31, 32),  # legs and feet
)  # fmt: skip
ALL = LandmarkSet(
    name="all",
    ids=tuple(range(33)),
    pairs=_ALL_PAIRS,
    bones=tuple(_ALL_BONES[i] for i in range(33)),
    # each face pair | shoulder | elbow | wrist + hand | hip | knee | ankle + foot
    swap_group=(0, 1, 2, 3, 4, 5, 6, 7, 7, 7, 7, 8, 9, 10, 10, 10),
)
LANDMARK_SETS = {s.name: s for s in (LIMBS, ALL)}

# Back-compatible names for the limb set (landmark, joint) and its display names.
LIMB_LANDMARKS: tuple[tuple[int, int], ...] = tuple(zip(LIMBS.ids, LIMBS.joints, strict=True))
LIMB_NAMES = tuple(n.replace("left_", "l_").replace("right_", "r_") for n in LIMBS.names)
LR_PAIRS = LIMBS.pairs


@dataclass(frozen=True)
class DetectionStats:
    """Per landmark of the set (L) unless said otherwise. Errors in crop sizes; `*_visible`
    over points the truth marks visible, `*_occluded` over the others."""

    n_crops: int
    err_median_visible: np.ndarray  # (L,)
    err_mean_visible: np.ndarray
    err_p90_visible: np.ndarray
    err_median_occluded: np.ndarray
    offset_mean: np.ndarray  # (L, 2) mean (detected - true) of visible inliers, u and v
    offset_sd: np.ndarray  # (L, 2) its standard deviation per axis
    outlier_visible: np.ndarray  # (L,) error > OUTLIER, not swapped, visible
    outlier_occluded: np.ndarray
    drop_visible: np.ndarray  # (L,) confidence < 0.5 where the truth is visible
    drop_occluded: np.ndarray  # (L,) where occluded
    occluded_rate: np.ndarray  # (L,) of the truth
    conf_hist_visible: np.ndarray  # (10,) confidence histogram of all the set's landmarks
    conf_hist_occluded: np.ndarray  # (10,)
    swap_rate: np.ndarray  # (P,) per left/right pair
    flip_rate: float  # crops with most pairs swapped
    presence_p05: float  # 5th percentile of the presence score
    n_visible: np.ndarray  # (L,) how many visible / occluded points the per-state numbers use
    n_occluded: np.ndarray
    n_pairs: np.ndarray  # (P,) countable crops per left/right pair

    def to_json(self) -> dict:
        return {
            k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()
        }

    @classmethod
    def from_json(cls, d: dict) -> DetectionStats:
        return cls(**{k: (np.asarray(v) if isinstance(v, list) else v) for k, v in d.items()})


def pair_swaps(
    det: np.ndarray,
    truth: np.ndarray,
    in_image: np.ndarray,
    pairs: tuple[tuple[int, int], ...] = LIMBS.pairs,
) -> tuple[np.ndarray, np.ndarray]:
    """det, truth (N, L, 2) in crop sizes; in_image (N, L) bool.
    Returns swapped (N, P) bool and countable (N, P) bool per left/right pair."""
    swapped = np.zeros((len(det), len(pairs)), bool)
    countable = np.zeros_like(swapped)
    for k, (a, b) in enumerate(pairs):
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


def swapped_landmarks(swapped: np.ndarray, pairs, n: int) -> np.ndarray:
    """(N, P) swapped pairs -> (N, L) landmarks that belong to a swapped pair."""
    out = np.zeros((len(swapped), n), bool)
    for k, (a, b) in enumerate(pairs):
        out[:, a] |= swapped[:, k]
        out[:, b] |= swapped[:, k]
    return out


def flipped_crops(swapped: np.ndarray, countable: np.ndarray) -> np.ndarray:
    n_count = countable.sum(1)
    return (n_count > 0) & (swapped.sum(1) * 2 > n_count)


def _hist(x: np.ndarray) -> np.ndarray:
    h, _ = np.histogram(np.clip(x, 0, 1), bins=CONF_BINS)
    return h / max(1, h.sum())


def _rate(flag: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Per-column mean of `flag` over the rows where `where` is set (NaN for none)."""
    n = where.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (flag & where).sum(0) / np.maximum(n, 1), np.nan)


def set_arrays(
    landmarks: np.ndarray, presence: np.ndarray, lset: LandmarkSet, crop_size: float
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 33, 3) detections -> the set's positions (N, L, 2) in crop sizes and confidences."""
    idx = list(lset.ids)
    return landmarks[:, idx, :2] / crop_size, landmarks[:, idx, 2] * presence[:, None]


def detection_stats(
    landmarks: np.ndarray,
    presence: np.ndarray,
    reference2d: np.ndarray,
    reference_visible: np.ndarray,
    crop_size: float,
    lset: LandmarkSet = LIMBS,
) -> DetectionStats:
    """landmarks (N, 33, 3) u, v crop px + visibility; presence (N,). The truth: for `LIMBS`
    joints2d (N, 24, 2) crop px and visible (N, 24) (the set picks its joints); for any set,
    its own reference points (N, L, 2) and visibility (N, L)."""
    det, conf = set_arrays(landmarks, presence, lset, crop_size)
    L = len(lset)
    if reference2d.shape[1] != L:  # joints of the LIMBS set
        if lset.joints is None:
            raise ValueError(f"set '{lset.name}' needs ({L}) reference points per crop")
        reference2d = reference2d[:, list(lset.joints)]
        reference_visible = reference_visible[:, list(lset.joints)]
    tru = reference2d / crop_size
    vis = reference_visible.astype(bool)
    occ = ~vis
    in_image = ((tru >= 0) & (tru <= 1)).all(-1)
    swapped, countable = pair_swaps(det, tru, in_image, lset.pairs)
    swapped_lm = swapped_landmarks(swapped, lset.pairs, L)
    diff = det - tru
    err = np.linalg.norm(diff, axis=-1)
    inlier = vis & ~swapped_lm & (err <= OUTLIER)

    def per_col(fn, mask):
        return np.array([fn(err[mask[:, k], k]) if mask[:, k].any() else np.nan for k in range(L)])

    def p90(x):
        return np.percentile(x, 90)

    def col_stat(fn):
        return np.stack(
            [
                fn(diff[inlier[:, k], k]) if inlier[:, k].any() else np.full(2, np.nan)
                for k in range(L)
            ]
        )

    return DetectionStats(
        n_crops=int(len(landmarks)),
        err_median_visible=per_col(np.median, vis),
        err_mean_visible=per_col(np.mean, vis),
        err_p90_visible=per_col(p90, vis),
        err_median_occluded=per_col(np.median, occ),
        offset_mean=col_stat(lambda x: x.mean(0)),
        offset_sd=col_stat(lambda x: x.std(0)),
        outlier_visible=_rate((err > OUTLIER) & ~swapped_lm, vis),
        outlier_occluded=_rate((err > OUTLIER) & ~swapped_lm, occ),
        drop_visible=_rate(conf < DROP_CONFIDENCE, vis),
        drop_occluded=_rate(conf < DROP_CONFIDENCE, occ),
        occluded_rate=occ.mean(0),
        conf_hist_visible=_hist(conf[vis]),
        conf_hist_occluded=_hist(conf[occ]),
        swap_rate=_rate(swapped, countable),
        flip_rate=float(flipped_crops(swapped, countable).mean()),
        presence_p05=float(np.percentile(presence, 5)),
        n_visible=vis.sum(0),
        n_occluded=occ.sum(0),
        n_pairs=countable.sum(0),
    )
