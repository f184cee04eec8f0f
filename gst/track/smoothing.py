"""One-Euro filtering (Casiez, Roussel and Vogel, CHI 2012) of per-person pose time series.

For each scalar x sampled at time t (te = t - t_prev):
    alpha(fc) = 1 / (1 + tau / te),  tau = 1 / (2 pi fc)
    dx        = (x - x_hat_prev) / te
    dx_hat    = alpha(d_cutoff) dx + (1 - alpha(d_cutoff)) dx_hat_prev
    fc        = min_cutoff + beta |dx_hat|
    x_hat     = alpha(fc) x + (1 - alpha(fc)) x_hat_prev
The first sample, and any sample with a value that is not finite (the state untouched), passes
through. Slow motion gets the low `min_cutoff` (less jitter), fast motion
raises the cutoff (less lag). Rotations are filtered as their 6D form (the first two columns of
the matrix) and mapped back by Gram-Schmidt, so the result is always a rotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OneEuroConfig:
    min_cutoff: float = 1.0  # Hz; lower = smoother at rest
    beta: float = 0.5  # cutoff gain per unit of speed; higher = less lag when moving
    d_cutoff: float = 1.0  # Hz; cutoff of the speed estimate

    def __post_init__(self):
        if self.min_cutoff <= 0 or self.d_cutoff <= 0 or self.beta < 0:
            raise ValueError(f"One-Euro needs min_cutoff > 0, d_cutoff > 0, beta >= 0; got {self}")


def _alpha(cutoff: np.ndarray | float, te: float) -> np.ndarray | float:
    tau = 1.0 / (2.0 * np.pi * cutoff)
    return 1.0 / (1.0 + tau / te)


class OneEuroFilter:
    """Element-wise One-Euro filter over arrays of a fixed shape."""

    def __init__(self, config: OneEuroConfig):
        self.config = config
        self.x_hat: np.ndarray | None = None
        self.dx_hat: np.ndarray | None = None
        self.t_prev: float | None = None

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if not np.isfinite(x).all():
            # no measurement: passed through, the state untouched (absorbed, one NaN made every
            # later estimate NaN for as long as the filter lived)
            return x.copy()
        if self.x_hat is None:
            self.x_hat, self.dx_hat, self.t_prev = x.copy(), np.zeros_like(x), float(t)
            return x.copy()
        te = float(t) - self.t_prev
        if te <= 0:
            raise ValueError(
                f"One-Euro samples must move forward in time, got t = {t} after {self.t_prev}"
            )
        c = self.config
        dx = (x - self.x_hat) / te
        a_d = _alpha(c.d_cutoff, te)
        self.dx_hat = a_d * dx + (1 - a_d) * self.dx_hat
        a = _alpha(c.min_cutoff + c.beta * np.abs(self.dx_hat), te)
        self.x_hat = a * x + (1 - a) * self.x_hat
        self.t_prev = float(t)
        return self.x_hat.copy()

    def state_dict(self) -> dict:
        if self.x_hat is None:
            return {}
        return {"x_hat": self.x_hat.tolist(), "dx_hat": self.dx_hat.tolist(), "t_prev": self.t_prev}

    def load_state_dict(self, state: dict) -> None:
        if not state:
            self.x_hat = self.dx_hat = self.t_prev = None
            return
        self.x_hat = np.asarray(state["x_hat"], dtype=np.float64)
        self.dx_hat = np.asarray(state["dx_hat"], dtype=np.float64)
        self.t_prev = float(state["t_prev"])


def rotmat_to_6d(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns."""
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def rot6d_to_rotmat(d6: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (Zhou et al. 2019)."""
    a, b = d6[..., :3], d6[..., 3:]
    x = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - np.sum(x * b, axis=-1, keepdims=True) * x
    y = b / np.linalg.norm(b, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


SMOOTHED_QUANTITIES = ("rotmats", "betas", "transl_cam", "joints_cam")


class PoseSmoother:
    """One filter per person and quantity; people appear and disappear with their tracks."""

    def __init__(self, config: OneEuroConfig):
        self.config = config
        self.filters: dict[int, dict[str, OneEuroFilter]] = {}

    def __call__(
        self, person_id: int, t: float, pose: dict[str, np.ndarray]
    ) -> dict[str, np.ndarray]:
        """Smooth one person's {rotmats (24,3,3), betas, transl_cam (3,), joints_cam (24,3)}."""
        filters = self.filters.setdefault(
            person_id, {k: OneEuroFilter(self.config) for k in SMOOTHED_QUANTITIES}
        )
        out = {}
        for k in SMOOTHED_QUANTITIES:
            if k == "rotmats":
                out[k] = rot6d_to_rotmat(filters[k](rotmat_to_6d(pose[k]), t))
            else:
                out[k] = filters[k](pose[k], t)
        return out

    def retain(self, live_ids: set[int]) -> None:
        """Forget people whose tracks ended."""
        self.filters = {i: f for i, f in self.filters.items() if i in live_ids}

    def state_dict(self) -> dict:
        return {
            str(i): {k: f.state_dict() for k, f in fs.items()} for i, fs in self.filters.items()
        }

    def load_state_dict(self, state: dict) -> None:
        self.filters = {}
        for i, fs in state.items():
            self.filters[int(i)] = {}
            for k in SMOOTHED_QUANTITIES:
                f = OneEuroFilter(self.config)
                f.load_state_dict(fs.get(k, {}))
                self.filters[int(i)][k] = f
