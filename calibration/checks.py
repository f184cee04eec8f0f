"""Plausibility checks of a rig against its capture volume (for imported calibrations too)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Rig


@dataclass(frozen=True)
class CaptureVolume:
    """An axis-aligned box in world coordinates (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, dtype=float), np.asarray(self.hi, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or np.any(hi <= lo):
            raise ValueError(
                f"capture volume needs finite lo < hi 3-vectors, got {self.lo}, {self.hi}"
            )

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2

    def corners(self) -> np.ndarray:
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        return np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )

    def ray_hits(self, origin: np.ndarray, direction: np.ndarray) -> bool:
        """Whether the ray origin + s * direction (s >= 0) meets the box (slab test)."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        d = np.asarray(direction, dtype=float)
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to a slab: effectively infinite t
        t1, t2 = (lo - origin) / d, (hi - origin) / d
        near, far = np.max(np.minimum(t1, t2)), np.min(np.maximum(t1, t2))
        return bool(far >= max(near, 0.0))


def axes_meeting_point(rig: Rig) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis line."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in rig:
        d = cam.optical_axis
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ cam.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def estimate_volume(rig: Rig, height: float = 2.0) -> CaptureVolume:
    """A plausible capture volume for a z-up rig: centred under the point where the optical
    axes meet, from the floor (z = 0) to `height`, half as wide as the cameras are far from it."""
    up = np.asarray(rig.up)
    if not np.allclose(up, [0, 0, 1]):
        raise ValueError(f"estimate_volume needs a z-up rig, this one's up axis is {rig.up}")
    c = axes_meeting_point(rig)
    dist = (
        np.median([np.linalg.norm(cam.center[:2] - c[:2]) for cam in rig]) if len(rig) > 1 else 2.0
    )
    half = max(0.35 * dist, 0.5)
    return CaptureVolume((c[0] - half, c[1] - half, 0.0), (c[0] + half, c[1] + half, height))


def check_rig(rig: Rig, volume: CaptureVolume | None = None) -> list[str]:
    """Problems found (empty when plausible): cameras at or below the floor (z-up rigs) and
    cameras whose optical axis misses the capture volume."""
    problems = []
    if np.allclose(rig.up, [0, 0, 1]):
        below = [f"{c.name} (z = {c.center[2]:.2f} m)" for c in rig if c.center[2] <= 0]
        if below:
            problems.append(f"cameras at or below the floor: {', '.join(below)}")
        volume = volume or estimate_volume(rig)
    if volume is not None:
        away = [c.name for c in rig if not volume.ray_hits(c.center, c.optical_axis)]
        if away:
            problems.append(
                f"optical axes miss the capture volume {volume.lo}..{volume.hi}: {away}"
            )
    return problems
