"""Camera response: exposure, vignetting, optical blur, sensor noise and sRGB encoding."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np


@dataclass(frozen=True)
class CameraResponse:
    """Per-camera image formation after the renderer's linear radiance."""

    exposure: float = 1.0  # linear gain
    vignetting: float = 0.25  # relative darkening at the image corners
    blur_sigma: float = 0.0  # Gaussian optical blur, pixels
    noise_sigma: float = 0.0  # noise std in 8-bit units at mid grey (read + shot noise)

    def __post_init__(self):
        if self.exposure <= 0:
            raise ValueError(f"exposure must be positive, got {self.exposure}")
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if self.blur_sigma < 0 or self.noise_sigma < 0:
            raise ValueError("blur_sigma and noise_sigma must be >= 0")


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function on [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(x: np.ndarray) -> np.ndarray:
    """Identity up to 0.8, then a soft roll-off toward 1 so bright kits do not clip flat."""
    knee = 0.8
    over = np.maximum(x - knee, 0)
    return np.where(x > knee, knee + (1 - knee) * (1 - np.exp(-over / (1 - knee))), x)


# Lookup table of tone curve + sRGB over linear [0, _LUT_MAX]: 2^18 entries stay within 0.02 of
# an 8-bit level of the exact curve, at a fraction of the cost of exp and pow per pixel.
_LUT_MAX = 4.0
_LUT_SIZE = 1 << 18
_LUT = (
    linear_to_srgb(tonemap(np.arange(_LUT_SIZE) * (_LUT_MAX / (_LUT_SIZE - 1)))) * 255.0
).astype(np.float32)


def encode_srgb(x: np.ndarray) -> np.ndarray:
    """Tone-mapped sRGB in 8-bit units (float32) of linear radiance x."""
    idx = (
        np.clip(x, 0.0, _LUT_MAX) * np.float32((_LUT_SIZE - 1) / _LUT_MAX) + np.float32(0.5)
    ).astype(np.int32)
    return _LUT[idx]


@lru_cache(maxsize=16)
def _vignette(h: int, w: int, strength: float) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (
        ((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2
    )
    return (1 - strength * r2).astype(np.float32)


def develop(radiance: np.ndarray, response: CameraResponse, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (H, W, 3) -> 8-bit BGR image (H, W, 3), as OpenCV writes videos."""
    h, w, _ = radiance.shape
    img = radiance.astype(np.float32) * np.float32(response.exposure)
    if response.vignetting > 0:
        img *= _vignette(h, w, float(response.vignetting))[..., None]
    if response.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), response.blur_sigma)
    srgb = encode_srgb(img)
    if response.noise_sigma > 0:
        # Read noise is flat, shot noise grows with the signal. Triangular noise (difference of
        # two uniforms, scaled to unit variance) is cheaper than normal draws and looks the same.
        std = np.float32(response.noise_sigma * np.sqrt(6.0)) * np.sqrt(
            np.float32(0.35) + srgb * np.float32(0.65 / 128.0)
        )
        tri = rng.random(srgb.shape, dtype=np.float32) - rng.random(srgb.shape, dtype=np.float32)
        srgb = srgb + tri * std
    out = np.clip(srgb + np.float32(0.5), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(out[..., ::-1])
