"""A learned check for BlazePose's whole-body left/right flips, from the crop's pixels.

BlazePose sometimes reads a person's left side as the right for the whole body (mostly side-on
views; gst.metrics.flips). The landmarks alone cannot tell (a mirrored skeleton is a plausible
body facing the other way), but the pixels can: face, chest and toes show which way the person
faces. A small CNN sees the crop at 64 px with two extra channels, Gaussian blobs at the left
and at the right landmarks, and scores

    s(crop, landmarks) = f(crop, left, right) - f(crop, right, left),

antisymmetric by construction: exchanging the labels negates the score. `s / temperature` is
the log-odds that the landmarks are mirrored on a balanced set; a crop is called mirrored when
the posterior log-odds, with the flip rate seen in training as the prior, are above 0.

Trained per scene, in `train`, on the training crops the rig's fused bodies label
(gst.train.flip_check); stored in the kept checkpoint's `extra["flip_check"]` (tensors and
numbers: weights_only loading) and applied before the network in `track` and `evaluate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.metrics.flips import unmirror

INPUT_SIZE = 64  # crops are square; the check sees them at this size
BLOB_SIGMA = 1.5  # px at INPUT_SIZE
MIN_CONFIDENCE = 0.5  # the hips and shoulders must be read at least this well for a decision
# BlazePose's left landmarks (odd ids; the nose, id 0, has no side) and their right partners
LEFT_IDS = tuple(i for i in range(33) if BLAZEPOSE_MIRROR[i] != i and i % 2 == 1)
RIGHT_IDS = tuple(int(BLAZEPOSE_MIRROR[i]) for i in LEFT_IDS)
_DECIDING_IDS = (11, 12, 23, 24)  # shoulders and hips, as gst.metrics.flips compares


class FlipCheckNet(nn.Module):
    """f(crop, left, right): (B, 5, 64, 64) -> (B,) (RGB in [0, 1], left blobs, right blobs)."""

    def __init__(self, width: int = 16):
        super().__init__()
        # the first layer strides (the cost of full-resolution layers buys nothing here)
        layers, c_in = [], 5
        for i, c_out in enumerate((width, 2 * width, 4 * width, 4 * width)):
            stride = 2 if i == 0 else 1
            layers += [nn.Conv2d(c_in, c_out, 3, stride, padding=1), nn.BatchNorm2d(c_out)]
            layers += [nn.ReLU()] + ([nn.MaxPool2d(2)] if i in (1, 2) else [])
            c_in = c_out
        self.features = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.head = nn.Sequential(nn.Dropout(0.3), nn.Linear(c_in, 1))
        self.width = width

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))[:, 0]

    def score(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) antisymmetric score: above 0 says the blobs' left/right labels are exchanged."""
        # one pass over both, so that batch norm's training statistics are shared
        out = self(torch.cat([x, exchange_sides(x)]))
        return out[: len(x)] - out[len(x) :]


def exchange_sides(x: torch.Tensor) -> torch.Tensor:
    """The check's input with the left and right landmark channels exchanged."""
    return x[:, [0, 1, 2, 4, 3]]


def check_input(images, landmarks) -> torch.Tensor:
    """(N, 5, 64, 64) float: square crops (N, S, S, 3) RGB uint8 (numpy or torch) resized to
    INPUT_SIZE, and blobs at their (N, 33, 3) landmarks (crop px, confidence; NaN: none)."""
    img = torch.as_tensor(np.asarray(images) if not torch.is_tensor(images) else images)
    lm = torch.as_tensor(
        np.asarray(landmarks) if not torch.is_tensor(landmarks) else landmarks
    ).float()
    if img.ndim != 4 or img.shape[-1] != 3 or img.shape[1] != img.shape[2]:
        raise ValueError(f"flip check: square RGB crops (N, S, S, 3) expected, got {img.shape}")
    if lm.shape != (len(img), 33, 3):
        raise ValueError(
            f"flip check: landmarks (N, 33, 3) for {len(img)} crops expected, got {tuple(lm.shape)}"
        )
    scale = INPUT_SIZE / img.shape[1]
    x = img.permute(0, 3, 1, 2).float() / 255.0
    if img.shape[1] != INPUT_SIZE:
        x = F.interpolate(x, size=(INPUT_SIZE, INPUT_SIZE), mode="area")
    grid = torch.arange(INPUT_SIZE, dtype=torch.float32)
    blobs = []
    for ids in (LEFT_IDS, RIGHT_IDS):
        p = lm[:, list(ids)]
        # pixel centres at integers in both (gst.model.landmarks)
        u = torch.nan_to_num((p[..., 0] + 0.5) * scale - 0.5, -100.0)
        v = torch.nan_to_num((p[..., 1] + 0.5) * scale - 0.5, -100.0)
        c = torch.nan_to_num(p[..., 2], 0.0).clamp(0, 1)
        gx = torch.exp(-((grid - u[..., None]) ** 2) / (2 * BLOB_SIGMA**2))  # (N, L, W)
        gy = torch.exp(-((grid - v[..., None]) ** 2) / (2 * BLOB_SIGMA**2))  # (N, L, H)
        g = gy[..., :, None] * gx[..., None, :] * c[..., None, None]
        blobs.append(g.amax(1))
    return torch.cat([x, torch.stack(blobs, 1)], 1)


def decidable(landmarks) -> np.ndarray:
    """(N,) bool: the hips and shoulders are read (confidence >= MIN_CONFIDENCE), the crops
    the check decides on; others are left as read."""
    lm = np.asarray(landmarks, np.float64)[:, list(_DECIDING_IDS)]
    return (np.isfinite(lm).all(-1) & (np.nan_to_num(lm[..., 2]) >= MIN_CONFIDENCE)).all(1)


@dataclass
class FlipCheck:
    """A trained check: the network, its temperature (scores / temperature are balanced
    log-odds) and `prior_log_odds`, log(p / (1 - p)) of the flip rate p seen in training."""

    net: FlipCheckNet
    temperature: float
    prior_log_odds: float
    batch_size: int = 256

    @torch.no_grad()
    def log_odds(self, images, landmarks) -> np.ndarray:
        """(N,) posterior log-odds that each crop's landmarks are mirrored."""
        self.net.eval()
        n = len(landmarks)
        out = np.zeros(n, np.float64)
        for s in range(0, n, self.batch_size):
            x = check_input(images[s : s + self.batch_size], landmarks[s : s + self.batch_size])
            out[s : s + len(x)] = self.net.score(x).double().numpy() / self.temperature
        return out + self.prior_log_odds

    def mirrored(self, images, landmarks) -> np.ndarray:
        """(N,) bool: the check calls the crop's landmarks mirrored (decidable crops only)."""
        flags = np.zeros(len(landmarks), dtype=bool)
        rows = np.flatnonzero(decidable(landmarks))
        if len(rows):
            flags[rows] = self.log_odds(images[rows], np.asarray(landmarks)[rows]) > 0
        return flags

    def correct(self, images, landmarks):
        """(landmarks with the mirrored crops' left/right labels exchanged, (N,) bool flags)."""
        flags = self.mirrored(images, landmarks)
        return unmirror(landmarks, flags), flags

    def to_state(self) -> dict:
        """Tensors and numbers for a checkpoint's `extra` (weights_only loading)."""
        return {
            "version": 1,
            "width": self.net.width,
            "temperature": float(self.temperature),
            "prior_log_odds": float(self.prior_log_odds),
            "weights": {k: v.detach().cpu() for k, v in self.net.state_dict().items()},
        }

    @classmethod
    def from_state(cls, state: dict, source: str = "checkpoint") -> FlipCheck:
        if not isinstance(state, dict) or state.get("version") != 1:
            raise ValueError(f"{source}: extra['flip_check'] is not a version-1 flip check")
        net = FlipCheckNet(int(state["width"]))
        try:
            net.load_state_dict(state["weights"])
        except (KeyError, RuntimeError) as exc:
            raise ValueError(f"{source}: the flip check's weights do not fit ({exc})") from None
        return cls(net.eval(), float(state["temperature"]), float(state["prior_log_odds"]))


def flip_check_of(extra: dict, source: str = "checkpoint") -> FlipCheck | None:
    """The flip check a checkpoint's `extra` holds, or None."""
    state = extra.get("flip_check") if extra else None
    return None if state is None else FlipCheck.from_state(state, source)
