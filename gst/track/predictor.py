"""The predictor contract: crops in, SMPL-layout body out, in the crop camera's frame.

A predictor is any callable

    predict(crops: (B, S, S, 3) uint8 RGB, K_crop: (B, 3, 3)) -> dict of numpy arrays
        rotmats    (B, 24, 3, 3)  [:, 0] = global orientation in the crop camera (OpenCV axes)
        betas      (B, nb)        shape coefficients (10 for SMPL)
        transl_cam (B, 3)         body translation, metres, crop camera frame
        joints_cam (B, 24, 3)     posed joints, metres, crop camera frame
        ...                       anything else (e.g. Gaussians) is passed through untouched

The crop camera has the same axes and origin as the full-frame camera (K_crop only rescales and
shifts K), so these are also full-camera-frame values.

Optional inputs, passed as keywords only to predictors that declare them: `landmarks=` (B, 33,
3) the crops' BlazePose landmarks, when `predictor.accepts_landmarks` is true; `up=` (B, 3) the
world's up direction in the camera frame, for calibrated cameras only, when
`predictor.accepts_up` is true (`gst.model.inference.GSTPredictor` declares both).

Optional method: `predictor.needs_pixels(landmarks (N, 33, 3)) -> (N,) bool`; the loop hands
crops for which it says False in blank, without cutting them (a predictor that takes those
crops' pose from their landmarks alone).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

NUM_JOINTS = 24

Predictor = Callable[[np.ndarray, np.ndarray], dict]


class PredictorOutputError(ValueError):
    """The predictor returned something that breaks the contract; the message names the key."""


@dataclass
class PoseBatch:
    rotmats: np.ndarray  # (B, 24, 3, 3) float64
    betas: np.ndarray  # (B, nb)
    transl_cam: np.ndarray  # (B, 3)
    joints_cam: np.ndarray  # (B, 24, 3)
    extra: dict  # other keys, untouched

    def __len__(self) -> int:
        return len(self.rotmats)

    def finite(self) -> np.ndarray:
        """(B,) True where every body value is finite."""
        parts = [self.rotmats, self.betas, self.transl_cam, self.joints_cam]
        return np.all(
            np.stack([np.isfinite(p).all(axis=tuple(range(1, p.ndim))) for p in parts]), axis=0
        )

    @staticmethod
    def concat(batches: list[PoseBatch], num_betas: int = 10) -> PoseBatch:
        if not batches:
            return PoseBatch(
                np.zeros((0, NUM_JOINTS, 3, 3)),
                np.zeros((0, num_betas)),
                np.zeros((0, 3)),
                np.zeros((0, NUM_JOINTS, 3)),
                {},
            )
        keys = set.intersection(*(set(b.extra) for b in batches))
        return PoseBatch(
            *(
                np.concatenate([getattr(b, k) for b in batches])
                for k in ("rotmats", "betas", "transl_cam", "joints_cam")
            ),
            {k: np.concatenate([np.asarray(b.extra[k]) for b in batches]) for k in keys},
        )

    def take(self, idx) -> PoseBatch:
        return PoseBatch(
            self.rotmats[idx],
            self.betas[idx],
            self.transl_cam[idx],
            self.joints_cam[idx],
            {k: np.asarray(v)[idx] for k, v in self.extra.items()},
        )


def _to_numpy(value, key: str) -> np.ndarray:
    if hasattr(value, "detach"):  # a torch tensor: accept it, the contract is about content
        value = value.detach().cpu().numpy()
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictorOutputError(f"predictor output '{key}' is not numeric ({exc})") from exc


def validate_prediction(out, batch: int) -> PoseBatch:
    """Check a predictor's output for a batch of `batch` crops and convert it to float64."""
    if not isinstance(out, dict):
        raise PredictorOutputError(f"predictor must return a dict, got {type(out).__name__}")
    expected = {
        "rotmats": (batch, NUM_JOINTS, 3, 3),
        "betas": (batch, None),
        "transl_cam": (batch, 3),
        "joints_cam": (batch, NUM_JOINTS, 3),
    }
    arrays = {}
    for key, shape in expected.items():
        if key not in out:
            raise PredictorOutputError(f"predictor output lacks '{key}' (has {sorted(out)})")
        arr = _to_numpy(out[key], key)
        if arr.ndim != len(shape) or any(
            s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)
        ):
            want = tuple("nb" if s is None else s for s in shape)
            raise PredictorOutputError(
                f"predictor output '{key}' has shape {arr.shape}, expected {want}"
            )
        arrays[key] = arr
    extra = {k: v for k, v in out.items() if k not in expected}
    return PoseBatch(
        arrays["rotmats"], arrays["betas"], arrays["transl_cam"], arrays["joints_cam"], extra
    )


def predict_batched(
    predict: Predictor, crops: np.ndarray, K_crop: np.ndarray, batch_size: int
) -> PoseBatch:
    """Run `predict` over crops in slices of `batch_size` and check each output."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    parts = []
    for i in range(0, len(crops), batch_size):
        c, k = crops[i : i + batch_size], K_crop[i : i + batch_size]
        parts.append(validate_prediction(predict(c, k), len(c)))
    return PoseBatch.concat(parts)
