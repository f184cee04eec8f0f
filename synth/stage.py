"""The room around the capture volume: a textured floor, walls and a ceiling, ray-cast analytically.

A stage is an axis-aligned box (floor z = 0) seen from inside. Its albedo is procedural in world
coordinates: a wooden court with lines for the sports hall, a dark mat with tape marks for the
dome, a carpeted lab for the H36M room. Lighting is a key light (a small area light, for soft
shadows) plus a sky-like ambient term.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from synth.appearance import srgb_to_linear
from synth.sampling import sample_image

SURFACES = ("floor", "ceiling", "wall")


@dataclass(frozen=True)
class Light:
    """Key light direction (unit, pointing from the scene to the light), its spread (radians)
    for soft shadows, and intensities of key and ambient light."""

    direction: tuple[float, float, float]
    spread: float = 0.08
    key: float = 2.4
    ambient: float = 0.75

    def samples(self, n: int) -> np.ndarray:
        """n fixed directions (n, 3) spread around `direction` (deterministic)."""
        d = np.asarray(self.direction, dtype=np.float64)
        d /= np.linalg.norm(d)
        if n <= 1:
            return d[None]
        a = np.cross(d, [1.0, 0.0, 0.0])
        if np.linalg.norm(a) < 1e-6:
            a = np.cross(d, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        ang = 2 * np.pi * (np.arange(n) + 0.5) / n
        r = self.spread * np.sqrt((np.arange(n) + 0.5) / n)
        out = d[None] + r[:, None] * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
        return out / np.linalg.norm(out, axis=1, keepdims=True)


@dataclass(frozen=True)
class Stage:
    """Room box [-half_x, half_x] x [-half_y, half_y] x [0, height] and its look."""

    style: str  # "court", "studio" or "lab"
    half_x: float
    half_y: float
    height: float
    light: Light
    seed: int = 0
    _noise: np.ndarray = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.style not in ("court", "studio", "lab"):
            raise ValueError(f"stage style '{self.style}' is not one of court, studio, lab")
        if min(self.half_x, self.half_y, self.height) <= 0:
            raise ValueError(
                f"stage box must have positive size, got {self.half_x}, {self.half_y}, "
                f"{self.height}"
            )
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x57A6E]))
        noise = rng.random((256, 256)).astype(np.float32)
        noise = cv2.GaussianBlur(np.tile(noise, (3, 3)), (0, 0), 2.0)[256:512, 256:512]  # tileable
        noise = (noise - noise.mean()) / (noise.std() + 1e-9)
        object.__setattr__(self, "_noise", noise.astype(np.float32))

    def to_dict(self) -> dict:
        return {
            "style": self.style,
            "half_x": self.half_x,
            "half_y": self.half_y,
            "height": self.height,
            "light": {
                "direction": list(self.light.direction),
                "spread": self.light.spread,
                "key": self.light.key,
                "ambient": self.light.ambient,
            },
        }

    def contains(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points)
        return (
            (np.abs(p[..., 0]) < self.half_x)
            & (np.abs(p[..., 1]) < self.half_y)
            & (p[..., 2] > 0)
            & (p[..., 2] < self.height)
        )

    # -- geometry -------------------------------------------------------------------------------
    def intersect(
        self, origin: np.ndarray, dirs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exit distance t (N,), surface id (N,) into SURFACES and inward normal (N, 3) of rays
        from `origin` (inside the box) along unit `dirs` (N, 3)."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        big = np.float64(1e9)
        with np.errstate(divide="ignore", invalid="ignore"):
            tz = np.where(
                d[:, 2] < 0,
                -o[2] / d[:, 2],
                np.where(d[:, 2] > 0, (self.height - o[2]) / d[:, 2], big),
            )
            tx = np.where(d[:, 0] != 0, (np.sign(d[:, 0]) * self.half_x - o[0]) / d[:, 0], big)
            ty = np.where(d[:, 1] != 0, (np.sign(d[:, 1]) * self.half_y - o[1]) / d[:, 1], big)
        t = np.minimum(tz, np.minimum(tx, ty))
        surf = np.where(t == tz, np.where(d[:, 2] < 0, 0, 1), 2)
        normal = np.zeros_like(d)
        normal[surf == 0, 2] = 1.0
        normal[surf == 1, 2] = -1.0
        wx = (surf == 2) & (t == tx)
        wy = (surf == 2) & ~wx
        normal[wx, 0] = -np.sign(d[wx, 0])
        normal[wy, 1] = -np.sign(d[wy, 1])
        return t, surf, normal

    # -- appearance -----------------------------------------------------------------------------
    def _tex(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Tileable smooth noise (zero mean, unit std) at texel coords u, v."""
        return sample_image(self._noise, np.mod(u, 256), np.mod(v, 256), border=cv2.BORDER_WRAP)

    def albedo(self, points: np.ndarray, surface: np.ndarray) -> np.ndarray:
        """Linear RGB albedo (N, 3) of stage points on the given surfaces."""
        p = np.asarray(points, dtype=np.float64)
        out = np.zeros((len(p), 3))
        floor, ceil, wall = surface == 0, surface == 1, surface == 2
        out[floor] = self._floor(p[floor])
        out[wall] = self._wall(p[wall])
        out[ceil] = srgb_to_linear((70, 72, 78))
        return out

    def _floor(self, p: np.ndarray) -> np.ndarray:
        x, y = p[:, 0], p[:, 1]
        if self.style == "court":
            plank_w, plank_l = 0.11, 2.4
            row = np.floor(y / plank_w)
            offset = np.mod(row * 0.37, 1.0) * plank_l
            col = np.floor((x + offset) / plank_l)
            h = np.mod(np.sin(row * 12.9898 + col * 78.233) * 43758.5453, 1.0)  # per-plank tone
            grain = self._tex(x * 12.0, y * 160.0)
            base = srgb_to_linear((196, 150, 98))[None] * (
                0.82 + 0.3 * h[:, None] + 0.05 * grain[:, None]
            )
            seam = (np.mod(y, plank_w) < 0.004) | (np.mod(x + offset, plank_l) < 0.004)
            base[seam] *= 0.7
            return self._court_lines(x, y, base)
        if self.style == "studio":
            base = srgb_to_linear((58, 60, 66))[None] * (
                1 + 0.06 * self._tex(x * 40, y * 40)[:, None]
            )
            tape = np.zeros(len(x), bool)
            for cx, cy in ((0, 0), (1.2, 0), (-1.2, 0), (0, 1.2), (0, -1.2)):
                tape |= ((np.abs(x - cx) < 0.15) & (np.abs(y - cy) < 0.025)) | (
                    (np.abs(y - cy) < 0.15) & (np.abs(x - cx) < 0.025)
                )
            ring = np.abs(np.hypot(x, y) - 2.0) < 0.025
            base[tape] = srgb_to_linear((220, 200, 60))
            base[ring] = srgb_to_linear((200, 200, 200))
            return base
        carpet = srgb_to_linear((92, 100, 104))[None] * (
            1
            + 0.12 * self._tex(x * 60, y * 60)[:, None]
            + 0.05 * self._tex(x * 5 + 50, y * 5)[:, None]
        )
        return carpet

    def _court_lines(self, x, y, base):
        """Handball-like court: 20 x 10 m (or smaller to fit), centre line, circle, areas."""
        hx, hy = min(10.0, self.half_x - 1.5), min(5.0, self.half_y - 1.5)
        w = 0.05
        line = ((np.abs(np.abs(x) - hx) < w) & (np.abs(y) <= hy + w)) | (
            (np.abs(np.abs(y) - hy) < w) & (np.abs(x) <= hx + w)
        )
        line |= (np.abs(x) < w) & (np.abs(y) <= hy)
        line |= np.abs(np.hypot(x, y) - 1.8) < w
        goal_area = (np.abs(x) > hx - 3.0) & (np.abs(x) <= hx) & (np.abs(y) < 3.0)
        base = base.copy()
        base[goal_area] = base[goal_area] * 0.4 + srgb_to_linear((40, 90, 170))[None] * 0.6
        base[line] = srgb_to_linear((235, 235, 230))
        return base

    def _wall(self, p: np.ndarray) -> np.ndarray:
        along = np.where(np.abs(np.abs(p[:, 0]) - self.half_x) < 1e-6, p[:, 1], p[:, 0])
        z = p[:, 2]
        if self.style == "court":
            out = np.tile(srgb_to_linear((205, 200, 188)), (len(p), 1))
            pad = z < 2.0
            out[pad] = srgb_to_linear((30, 70, 140))
            out[np.abs(z - 2.0) < 0.03] = srgb_to_linear((240, 240, 240))
            seam = (np.mod(along, 2.5) < 0.03) & ~pad
            out[seam] *= 0.6
            return out * (1 + 0.04 * self._tex(along * 20, z * 20)[:, None])
        if self.style == "studio":
            out = np.tile(srgb_to_linear((150, 152, 158)), (len(p), 1))
            seam = (np.mod(along, 1.0) < 0.02) | (np.mod(z, 1.0) < 0.02)
            out[seam] *= 0.55
            out[z < 0.12] = srgb_to_linear((40, 40, 44))
            return out
        out = np.tile(srgb_to_linear((180, 170, 150)), (len(p), 1))
        out[z < 0.1] = srgb_to_linear((60, 55, 50))
        curtain = np.abs(along) < 1.5
        out[curtain & (z > 0.1)] = (
            srgb_to_linear((35, 35, 40))
            * (1 + 0.25 * np.sin(along[curtain & (z > 0.1)] * 25))[:, None]
        )
        return out

    def shade(
        self,
        albedo: np.ndarray,
        normal: np.ndarray,
        light_dirs: np.ndarray,
        visibility: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ambient and direct radiance (N, 3) each; direct is scaled by mean `visibility`
        (N, n_lights) when given."""
        ambient = albedo * (self.light.ambient * (0.8 + 0.2 * normal[:, 2:3]))
        L = np.asarray(light_dirs, dtype=normal.dtype)
        cos = np.clip(
            normal[:, 0:1] * L[:, 0] + normal[:, 1:2] * L[:, 1] + normal[:, 2:3] * L[:, 2], 0, None
        )
        if visibility is not None:
            cos = cos * visibility
        direct = albedo * (self.light.key * cos.mean(1, keepdims=True))
        return ambient, direct


def stage_for_rig(kind: str, seed: int = 0) -> Stage:
    """The room that goes with a rig kind (see `synth.rigs`)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x11647]))
    az = rng.uniform(0, 2 * np.pi)
    if kind == "hall":
        elev = np.deg2rad(rng.uniform(62, 75))
        style, hx, hy, h = "court", 13.0, 9.0, 8.0
    elif kind == "dome":
        elev = np.deg2rad(rng.uniform(55, 70))
        style, hx, hy, h = "studio", 4.6, 4.6, 4.8
    elif kind == "h36m":
        elev = np.deg2rad(rng.uniform(50, 65))
        style, hx, hy, h = "lab", 4.3, 4.0, 3.6
    else:
        raise ValueError(f"unknown rig kind '{kind}' for a stage")
    d = (np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev))
    return Stage(
        style=style,
        half_x=hx,
        half_y=hy,
        height=h,
        light=Light(direction=tuple(float(v) for v in d)),
        seed=seed,
    )
