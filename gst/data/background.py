"""Background models for static cameras: temporal median, or OpenCV's MOG2 / KNN.

Each model first learns from frames sampled across the whole video (so a person standing in the
first frames does not become background), then labels every frame with the model frozen:
`foreground(frame)` returns a boolean mask with shadows removed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

METHODS = ("median", "mog2", "knn")


@dataclass(frozen=True)
class BackgroundConfig:
    """How foreground is told from background. Distances are in 8-bit colour units."""

    method: str = "median"
    samples: int = 60  # frames sampled evenly across the video to learn the background
    threshold: float = 35.0  # median: colour distance that certainly is foreground
    low_threshold: float = 18.0  # median: weaker distance kept when connected to a certain pixel
    # Brightness ratio I/B range in which an unchanged colour is a lighting change, not a
    # person: below 1 cast shadows, above 1 a shadow that the background model itself holds.
    shadow_ratio: tuple[float, float] = (0.45, 1.5)
    shadow_chroma: float = 12.0  # median: max colour change (after brightness) for a shadow
    edge_fraction: float = (
        0.5  # median: a silhouette-edge pixel needs this share of the inner contrast
    )
    edge_radius: int = 2  # median: width (px) of the silhouette edge that is refined
    mog2_var_threshold: float = 16.0
    knn_dist2_threshold: float = 400.0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(
                f"background method '{self.method}' is unknown; expected one of {METHODS}"
            )
        if self.samples < 3:
            raise ValueError(f"background samples must be >= 3, got {self.samples}")
        if not 0 < self.low_threshold <= self.threshold:
            raise ValueError(
                f"need 0 < low_threshold <= threshold, got {self.low_threshold}, {self.threshold}"
            )
        lo, hi = self.shadow_ratio
        if not 0 < lo < 1 <= hi:
            raise ValueError(f"shadow_ratio must satisfy 0 < lo < 1 <= hi, got {self.shadow_ratio}")


class BackgroundModel(Protocol):
    def foreground(self, frame: np.ndarray) -> np.ndarray:
        """Boolean foreground mask (H, W) of a BGR frame."""
        ...


def sample_indices(n_frames: int, samples: int) -> list[int]:
    """Up to `samples` frame indices spread evenly over [0, n_frames)."""
    k = min(samples, n_frames)
    return sorted(set(np.linspace(0, n_frames - 1, k).round().astype(int).tolist()))


def hysteresis(strong: np.ndarray, weak: np.ndarray) -> np.ndarray:
    """Pixels of `weak` that are 8-connected to a pixel of `strong` (strong implies weak)."""
    n, labels = cv2.connectedComponents(weak.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(weak, dtype=bool)
    keep = np.zeros(n, dtype=bool)
    keep[np.unique(labels[strong])] = True
    keep[0] = False
    return keep[labels]


def refine_edges(fg: np.ndarray, dist: np.ndarray, fraction: float, radius: int) -> np.ndarray:
    """Drop silhouette-edge pixels that are more background than person.

    Blur (lens, motion, video compression) mixes person and background colours along the
    outline, so a fixed threshold makes silhouettes fat. An edge pixel is kept only if its
    distance to the background is at least `fraction` of the largest distance found just inside
    the silhouette nearby, i.e. if it is mostly person.
    """
    if fraction <= 0 or radius <= 0:
        return fg
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    m = fg.astype(np.uint8)
    inner = cv2.erode(m, k)
    edge = fg & (inner == 0)
    inner_max = cv2.dilate(dist.astype(np.float32) * inner, k)
    return fg & (~edge | (dist >= fraction * inner_max))


class MedianBackground:
    """Per-pixel temporal median of sampled frames; colour distance with shadow suppression.

    A pixel is a shadow (not foreground) when it is a darker copy of the background: its
    brightness ratio alpha = <I, B> / |B|^2 lies in `shadow_ratio` and what remains after
    scaling, |I - alpha B|, is small (Horprasert et al. 1999).
    """

    def __init__(
        self, samples: np.ndarray, config: BackgroundConfig, median: np.ndarray | None = None
    ):
        if samples.ndim != 4 or samples.shape[-1] != 3:
            raise ValueError(f"background samples must be (N, H, W, 3), got {samples.shape}")
        self.config = config
        median = temporal_median(samples) if median is None else median
        self.background = median.astype(np.float32)
        self._inv_bg_norm2 = 1.0 / np.maximum(_channel_sum(self.background * self.background), 1.0)

    def foreground(self, frame: np.ndarray) -> np.ndarray:
        cfg = self.config
        img = frame.astype(np.float32)
        diff = cv2.subtract(img, self.background)
        dist = cv2.sqrt(_channel_sum(cv2.multiply(diff, diff)))
        weak = dist > cfg.low_threshold
        # Brightness ratio alpha = <I, B> / |B|^2 and what is left after it, |I - alpha B|^2 =
        # |I|^2 - <I, B>^2 / |B|^2 (colour change).
        dot = _channel_sum(cv2.multiply(img, self.background))
        alpha = dot * self._inv_bg_norm2
        chroma2 = _channel_sum(cv2.multiply(img, img)) - dot * alpha
        lo, hi = cfg.shadow_ratio
        light = (alpha >= lo) & (alpha <= hi) & (chroma2 < cfg.shadow_chroma**2)
        weak &= ~light
        strong = weak & (dist > cfg.threshold)
        fg = hysteresis(strong, weak)
        return refine_edges(fg, dist, cfg.edge_fraction, cfg.edge_radius)


def temporal_median(samples: np.ndarray) -> np.ndarray:
    """Per-pixel median over axis 0 (the lower middle value for an even count), computed with
    a partial sort in the samples' own dtype: no float copy of the whole stack."""
    k = (len(samples) - 1) // 2
    return np.partition(samples, k, axis=0)[k]


def temporal_medians(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From one partial sort over axis 0: `temporal_median` (the lower middle value) and
    `np.median`'s answer (float64, the mean of the two middle values for an even count)."""
    lo, hi = (len(samples) - 1) // 2, len(samples) // 2
    part = np.partition(samples, [lo, hi] if hi != lo else lo, axis=0)
    return part[lo], (part[lo].astype(np.float64) + part[hi]) / 2


def _channel_sum(img: np.ndarray) -> np.ndarray:
    """Sum over the colour channels of an (H, W, 3) float32 image, via OpenCV (fast)."""
    return cv2.transform(img, np.ones((1, 3), np.float32))


KNN_SAMPLES = 20  # samples per pixel the KNN subtractor keeps


class OpenCVBackground:
    """cv2 MOG2 or KNN subtractor with shadow detection, trained on the samples then frozen."""

    def __init__(
        self, samples: np.ndarray, config: BackgroundConfig, median: np.ndarray | None = None
    ):
        self.config = config
        n = len(samples)
        if config.method == "knn":
            # KNN keeps KNN_SAMPLES per pixel and fills them over the frames it is fed: fewer
            # frames (a short clean plate or clip) left them unfilled and every pixel foreground.
            # Feed the samples cyclically up to that count (unchanged from KNN_SAMPLES on).
            n = max(n, KNN_SAMPLES)
        if config.method == "mog2":
            self.sub = cv2.createBackgroundSubtractorMOG2(
                history=n, varThreshold=config.mog2_var_threshold, detectShadows=True
            )
            # Colours seen in fewer than 40% of the samples are not background (OpenCV's
            # default 0.9 lets anyone who stood somewhere 10% of the clip become background).
            self.sub.setBackgroundRatio(0.6)
        else:
            self.sub = cv2.createBackgroundSubtractorKNN(
                history=n, dist2Threshold=config.knn_dist2_threshold, detectShadows=True
            )
            # Same idea for KNN: keep more samples per pixel and ask more of them to agree.
            self.sub.setNSamples(KNN_SAMPLES)
            self.sub.setkNNSamples(6)
        self.sub.setShadowThreshold(float(config.shadow_ratio[0]))
        cv2.setRNGSeed(0)  # KNN samples at random: make runs repeatable
        # The subtractors trust their first frame most; start them from the temporal median
        # (the best single guess of the empty scene) rather than from whoever is in frame 0.
        median = temporal_median(samples) if median is None else median
        self.sub.apply(np.ascontiguousarray(median), learningRate=1.0)
        for i in range(n):
            self.sub.apply(samples[i % len(samples)], learningRate=-1)

    def foreground(self, frame: np.ndarray) -> np.ndarray:
        # 255 = foreground, 127 = shadow, 0 = background; the model stays frozen.
        return self.sub.apply(frame, learningRate=0) == 255


def build_background(
    samples: np.ndarray, config: BackgroundConfig, median: np.ndarray | None = None
) -> BackgroundModel:
    """Learn the background model named by `config.method` from (N, H, W, 3) BGR samples.
    `median`: their `temporal_median`, when the caller has it already (it is not recomputed)."""
    if len(samples) == 0:
        raise ValueError("no background samples")
    if config.method == "median":
        return MedianBackground(samples, config, median)
    return OpenCVBackground(samples, config, median)
