"""Synthetic camera rigs: a CMU-dome-like sphere section, an H36M-like room, a sports hall.

All cameras look at the capture volume (`rig.meta["volume_center"]`, radius
`rig.meta["volume_radius"]`). World: metres, Z up, floor z = 0 (see `synth.world`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration import Camera, Rig
from synth.world import WORLD_UP

H36M_CAMERA_IDS = ("54138969", "55011271", "58860488", "60457274")


@dataclass(frozen=True)
class RigKind:
    """Defaults of one kind of capture space."""

    n_cameras: int
    width: int
    height: int
    fov_deg: float  # horizontal field of view of the pinhole model
    fps: float
    volume_center: tuple[float, float, float]
    volume_radius: float  # horizontal radius people move in, metres


RIG_KINDS = {
    # CMU Panoptic: HD cameras on a 5.5 m dome, 29.97 fps.
    "dome": RigKind(24, 1920, 1080, 70.0, 29.97, (0.0, 0.0, 0.95), 1.5),
    # Human3.6M: 4 cameras in the corners of a room, ~1000x1000 at 50 fps, f ~ 1145 px.
    "h36m": RigKind(4, 1000, 1002, 47.0, 50.0, (0.0, 0.0, 0.9), 1.5),
    # Sports hall: 8 cameras 3 m up around a court, 50 fps.
    "hall": RigKind(8, 1920, 1080, 55.0, 50.0, (0.0, 0.0, 1.0), 3.0),
}


def look_at(
    name: str,
    center: np.ndarray,
    target: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    width: int,
    height: int,
    roll: float = 0.0,
    meta: dict | None = None,
) -> Camera:
    """An OpenCV camera at `center` looking at `target` with world Z up (image y down)."""
    center = np.asarray(center, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, WORLD_UP)
    if np.linalg.norm(right) < 1e-6:
        raise ValueError(f"camera '{name}' looks straight up or down; give it a tilted target")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    c, s = np.cos(roll), np.sin(roll)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
    return Camera.create(name, K, dist, R, -R @ center, width, height, meta=meta or {})


def _positions(kind: str, n: int, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """Camera names and centres (n, 3) for a rig kind."""
    if kind == "dome":
        # Spherical section around (0, 0, 1.0), radius 3.2 m, elevations -10..45 degrees,
        # azimuths spread by the golden angle so any count covers the sphere evenly.
        radius, centre_z = 3.2, 1.0
        k = np.arange(n)
        az = np.mod(k * 2.399963 + rng.uniform(0, 2 * np.pi), 2 * np.pi)
        elev = np.deg2rad(-10 + 55 * ((k * 0.618034 + 0.31) % 1.0))
        pos = np.stack(
            [
                radius * np.cos(elev) * np.cos(az),
                radius * np.cos(elev) * np.sin(az),
                centre_z + radius * np.sin(elev),
            ],
            -1,
        )
        return [f"00_{i:02d}" for i in range(n)], pos
    if kind == "h36m":
        # Room corners first, then along the walls: cameras at chest height, 4.3-4.8 m away.
        hx, hy = 3.4, 3.0
        corners = [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
        perim = np.array(corners + [(0, hy), (-hx, 0), (0, -hy), (hx, 0)])
        ring = np.arange(n) // len(perim)  # more than 8 cameras: further rings, higher and closer
        xy = np.array([perim[i % len(perim)] * 0.93 ** ring[i] for i in range(n)])
        z = np.minimum(rng.uniform(1.45, 1.85, n) + 0.45 * ring, 3.3)
        names = [H36M_CAMERA_IDS[i] if i < 4 else f"h36m_{i:02d}" for i in range(n)]
        return names, np.c_[xy + rng.uniform(-0.15, 0.15, (n, 2)), z]
    if kind == "hall":
        # Ellipse around the court, 3 m up (a little jitter: real mounts are not perfect).
        ang = 2 * np.pi * (np.arange(n) + 0.5) / n + rng.uniform(-0.08, 0.08, n)
        xy = np.stack([7.0 * np.cos(ang), 5.0 * np.sin(ang)], -1)
        z = 3.0 + rng.uniform(-0.1, 0.1, n)
        return [f"hall_{i:02d}" for i in range(n)], np.c_[xy, z]
    raise ValueError(f"unknown rig kind '{kind}', expected one of {sorted(RIG_KINDS)}")


def sample_distortion(spec, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) OpenCV distortion [k1, k2, p1, p2, k3] from a spec: None/'none', 'mild',
    'strong', or explicit coefficients (4 or 5 numbers, used for every camera).

    Sampled distortion is radial only (p1 = p2 = 0): every format synth writes (rig.json,
    Panoptic, H36M's own lens model) then represents the cameras exactly."""
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return np.zeros((n, 5))
    if isinstance(spec, str):
        ranges = {
            "mild": ((-0.12, -0.03), (0.0, 0.05), (0.0, 0.005)),
            "strong": ((-0.3, -0.2), (0.05, 0.12), (0.0, 0.02)),
        }
        if spec not in ranges:
            raise ValueError(
                f"distortion '{spec}' is not known; use 'none', 'mild', 'strong' or 4-5 "
                "coefficients"
            )
        (a, b), (c, d), (e, f) = ranges[spec]
        return np.stack(
            [
                rng.uniform(a, b, n),
                rng.uniform(c, d, n),
                np.zeros(n),
                np.zeros(n),
                rng.uniform(e, f, n),
            ],
            -1,
        )
    coeffs = np.asarray(spec, dtype=np.float64).ravel()
    if coeffs.size not in (4, 5) or not np.all(np.isfinite(coeffs)):
        raise ValueError(
            "distortion coefficients must be 4 or 5 finite numbers (k1, k2, p1, p2[, k3]), got "
            f"{spec!r}"
        )
    return np.tile(np.pad(coeffs, (0, 5 - coeffs.size)), (n, 1))


def _folds(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> bool:
    """True if the radial distortion folds back before it reaches 1.25x the image's radius
    (pixels would see two directions). The image's corners are distorted radii; the slope
    d r_d / d r is a function of the undistorted radius r, so it is checked over every r whose
    distorted radius is still inside 1.25x the corners' (for a barrel lens that r is larger
    than the corners' own radius: checking up to it missed folds inside the image)."""
    k1, k2, _, _, k3 = dist
    corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], dtype=np.float64)
    r_img = np.max(np.linalg.norm((corners - K[:2, 2]) / [K[0, 0], K[1, 1]], axis=1))
    # while the slope stays above 0.05, r_d grows at least 0.05 r: 25x the target is enough
    r = np.linspace(0, 25 * 1.25 * r_img, 20001)
    r_d = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    slope = 1 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6
    bent = np.flatnonzero(slope <= 0.05)
    reached = np.flatnonzero(r_d >= 1.25 * r_img)
    if not len(bent):
        return False
    return not len(reached) or bent[0] <= reached[0]


FOV_MIN_DEG, FOV_MAX_DEG = 5.0, 150.0  # a camera's horizontal field, either way given


def make_rig(
    kind: str,
    n_cameras: int | None = None,
    width: int | None = None,
    height: int | None = None,
    focal_mm: float | None = None,
    fov_deg: float | None = None,
    sensor_width_mm: float = 36.0,
    distortion: str | Sequence[float] | None = None,
    fps: float | None = None,
    seed: int = 0,
) -> Rig:
    """Build a synthetic rig of `kind` ('dome', 'h36m' or 'hall').

    Focal length comes from `focal_mm` on a sensor `sensor_width_mm` wide (35 mm equivalent by
    default) or from the horizontal `fov_deg`; the kind's default fov otherwise. `fps` and the
    capture volume are stored in `rig.meta`. Deterministic from `seed`.
    """
    if kind not in RIG_KINDS:
        raise ValueError(f"unknown rig kind '{kind}', expected one of {sorted(RIG_KINDS)}")
    d = RIG_KINDS[kind]
    n = d.n_cameras if n_cameras is None else int(n_cameras)
    width = d.width if width is None else int(width)
    height = d.height if height is None else int(height)
    fps = d.fps if fps is None else float(fps)
    if n < 1:
        raise ValueError(f"rig '{kind}': n_cameras must be >= 1, got {n}")
    if width < 16 or height < 16:
        raise ValueError(f"rig '{kind}': image size {width}x{height} is too small (min 16x16)")
    if fps <= 0:
        raise ValueError(f"rig '{kind}': fps must be positive, got {fps}")
    if focal_mm is not None and fov_deg is not None:
        raise ValueError(f"rig '{kind}': give focal_mm or fov_deg, not both")
    if focal_mm is not None:
        if focal_mm <= 0 or sensor_width_mm <= 0:
            raise ValueError(f"rig '{kind}': focal_mm and sensor_width_mm must be positive")
        f = focal_mm / sensor_width_mm * width
        # the field fov_deg is held to: 1 mm on the default sensor was a 174 degree pinhole,
        # 1e-6 mm a focal length of 2e-6 px, infinity (or NaN) a camera matrix of inf
        fov = float(np.degrees(2 * np.arctan(sensor_width_mm / 2 / focal_mm)))
        if not FOV_MIN_DEG <= fov <= FOV_MAX_DEG:
            raise ValueError(
                f"rig '{kind}': focal_mm {focal_mm} on a {sensor_width_mm} mm sensor is a "
                f"{fov:.1f} degree field of view; it must be within [{FOV_MIN_DEG:g}, "
                f"{FOV_MAX_DEG:g}] as fov_deg's"
            )
    else:
        fov = d.fov_deg if fov_deg is None else float(fov_deg)
        if not FOV_MIN_DEG <= fov <= FOV_MAX_DEG:
            raise ValueError(
                f"rig '{kind}': fov_deg must be within [{FOV_MIN_DEG:g}, {FOV_MAX_DEG:g}], "
                f"got {fov}"
            )
        f = width / 2 / np.tan(np.deg2rad(fov) / 2)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x416]))
    names, centres = _positions(kind, n, rng)
    dists = sample_distortion(distortion, n, rng)
    target0 = np.asarray(d.volume_center)
    cams = []
    for i, (name, c) in enumerate(zip(names, centres, strict=True)):
        cx = width / 2 + rng.uniform(-0.01, 0.01) * width
        cy = height / 2 + rng.uniform(-0.01, 0.01) * height
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        if isinstance(distortion, str):
            while _folds(K, dists[i], width, height):  # sampled: tame it for wide lenses
                dists[i] *= 0.8
        elif _folds(K, dists[i], width, height):
            raise ValueError(
                f"camera '{name}': distortion {dists[i].tolist()} folds over within the image "
                f"(fov {np.degrees(2 * np.arctan(width / 2 / f)):.0f} deg); reduce k1/k2"
            )
        target = (
            target0 + np.r_[rng.uniform(-0.15, 0.15, 2) * d.volume_radius, rng.uniform(-0.1, 0.1)]
        )
        roll = np.deg2rad(rng.uniform(-1.5, 1.5))
        cams.append(
            look_at(name, c, target, K, dists[i], width, height, roll, meta={"source": "synth"})
        )
    meta = {
        "fps": fps,
        "kind": kind,
        "volume_center": list(d.volume_center),
        "volume_radius": d.volume_radius,
        "seed": int(seed),
        "source": "synth",
    }
    return Rig(tuple(cams), up=WORLD_UP, meta=meta)
