"""Small synthetic multi-camera scenes with exact person masks, for the extraction tests.

A textured floor and a striped cylindrical wall are static; people are sets of shaded ellipsoids
(head, torso, hips, arms, legs) walking along known 3D paths. Every pixel is ray-cast through
the calibrated (distorted) camera, so masks and ids are exact and occlusions are right. The
layout follows the synthetic-scene contract: videos/<cam>.mp4, truth/masks/<cam>.npz (uint8 id
masks, 0 = background).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration import Camera, Rig

# Body parts: (centre in body frame (x right, y forward, z up), radii, colour slot)
_PARTS = [
    ((0.0, 0.0, 1.62), (0.10, 0.11, 0.12), "skin"),  # head
    ((0.0, 0.0, 1.25), (0.19, 0.12, 0.26), "shirt"),  # torso
    ((0.0, 0.0, 0.95), (0.17, 0.11, 0.12), "pants"),  # hips
    ((-0.26, 0.0, 1.20), (0.055, 0.055, 0.28), "shirt"),  # arms
    ((0.26, 0.0, 1.20), (0.055, 0.055, 0.28), "shirt"),
    ((-0.09, 0.0, 0.46), (0.075, 0.075, 0.44), "pants"),  # legs
    ((0.09, 0.0, 0.46), (0.075, 0.075, 0.44), "pants"),
]

_OUTFITS = [
    {"skin": (120, 150, 200), "shirt": (40, 40, 200), "pants": (120, 60, 30)},
    {"skin": (90, 120, 170), "shirt": (60, 170, 60), "pants": (50, 50, 60)},
    {"skin": (110, 140, 190), "shirt": (200, 120, 40), "pants": (160, 160, 160)},
]


@dataclass
class SynthScene:
    root: Path
    rig: Rig
    videos: dict[str, Path]
    truth: Path  # <root>/truth
    n_frames: int
    n_people: int


def ring_rig(
    n_cams: int = 4,
    radius: float = 5.0,
    height: float = 2.4,
    size=(320, 240),
    f: float = 300.0,
    distort: bool = True,
    target=(0.0, 0.0, 1.0),
) -> Rig:
    """Cameras on a circle around the origin, looking at `target`; z is up."""
    cams = []
    w, h = size
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams + 0.3
        C = np.array([radius * np.cos(a), radius * np.sin(a), height])
        z = np.asarray(target) - C
        z /= np.linalg.norm(z)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        dist = [-0.08 + 0.02 * i, 0.02, 0.001, -0.001, 0.0] if distort else []
        K = [
            [f * (1 + 0.02 * i), 0, w / 2 - 0.5 + 3 * i],
            [0, f * (1 + 0.02 * i), h / 2 - 0.5 - 2 * i],
            [0, 0, 1],
        ]
        cams.append(Camera.create(f"cam{i}", K, dist, R, -R @ C, w, h))
    return Rig(tuple(cams))


def _rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    d = cam.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    return cam.center, d


def _background(cam: Camera, origin: np.ndarray, d: np.ndarray, rng_seed: int = 0) -> np.ndarray:
    """Textured floor (z = 0) and a striped cylinder wall of radius 9 m."""
    n = len(d)
    img = np.zeros((n, 3), np.float32)
    down = d[:, 2] < -1e-6
    t_floor = np.where(down, -origin[2] / np.where(down, d[:, 2], -1.0), 1e9)
    # Wall: |origin_xy + t d_xy| = 9
    a = (d[:, :2] ** 2).sum(1)
    b = 2 * (d[:, :2] @ origin[:2])
    c = (origin[:2] ** 2).sum() - 81.0
    t_wall = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / (2 * np.maximum(a, 1e-12))
    floor = t_floor < t_wall
    p = origin + t_floor[:, None] * d
    checker = ((np.floor(p[:, 0] / 0.5) + np.floor(p[:, 1] / 0.5)) % 2)[floor]
    noise = np.sin(p[floor, 0] * 7.3) * np.sin(p[floor, 1] * 5.1)
    img[floor] = np.stack(
        [150 + 40 * checker + 15 * noise, 140 + 30 * checker, 120 + 20 * noise], 1
    )
    q = origin + t_wall[:, None] * d
    ang = np.arctan2(q[:, 1], q[:, 0])
    stripe = (np.sin(ang * 40) > 0).astype(np.float32)
    wall = ~floor
    img[wall] = np.stack(
        [
            90 + 60 * stripe[wall],
            160 + 30 * np.cos(q[wall, 2] * 3),
            180 - 50 * stripe[wall] + 20 * np.sin(ang[wall] * 7),
        ],
        1,
    )
    return img.clip(0, 255)


def person_pose(k: int, frame: int, n_frames: int, laps: float = 1.0) -> tuple[np.ndarray, float]:
    """Position (x, y on the floor) and heading of person k at a frame: `laps` circles around
    the middle over the clip, in opposite directions, so people cross and occlude each other."""
    s = laps * frame / max(1, n_frames)
    radius = (1.5, 0.9, 1.9)[k % 3]
    direction = (1, -1, 1)[k % 3]
    a = direction * 2 * np.pi * s + 2.1 * k
    pos = np.array([radius * np.cos(a), radius * np.sin(a)])
    heading = a + direction * np.pi / 2
    return pos, heading


def _render_people(origin, d, people_ellipsoids):
    """Nearest hit per ray: (t, person id (1-based, 0 none), colour)."""
    n = len(d)
    best_t = np.full(n, np.inf, np.float64)
    pid = np.zeros(n, np.uint8)
    col = np.zeros((n, 3), np.float32)
    light = np.array([0.3, -0.4, 0.86])
    light /= np.linalg.norm(light)

    def near(idx, centre, radius):
        # Rays (among idx) passing within `radius` of `centre`: cheap culling before the exact test.
        v = centre - origin
        along = d[idx] @ v
        return idx[(v @ v - along**2 <= radius**2) & (along > 0)]

    all_rays = np.arange(n)
    for person, ellipsoids in enumerate(people_ellipsoids, start=1):
        body_centre = np.mean([e[0] for e in ellipsoids], axis=0)
        body_r = max(np.linalg.norm(e[0] - body_centre) + max(e[2]) for e in ellipsoids)
        body_rays = near(all_rays, body_centre, body_r)
        for centre, Rb, radii, colour in ellipsoids:
            idx = near(body_rays, centre, max(radii))
            if len(idx) == 0:
                continue
            o = ((origin - centre) @ Rb) / radii
            dd = (d[idx] @ Rb) / radii
            a = (dd**2).sum(1)
            b = 2 * (dd @ o)
            c = o @ o - 1
            disc = b * b - 4 * a * c
            hit = disc > 0
            t = np.full(len(idx), np.inf)
            t[hit] = (-b[hit] - np.sqrt(disc[hit])) / (2 * a[hit])
            closer = hit & (t > 0) & (t < best_t[idx])
            if not closer.any():
                continue
            sel = idx[closer]
            best_t[sel] = t[closer]
            pid[sel] = person
            # Ellipsoid normal for shading.
            pl = o + t[closer, None] * dd[closer]
            nrm = (pl / radii) @ Rb.T
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            shade = 0.55 + 0.45 * np.clip(nrm @ light, 0, 1)
            col[sel] = np.asarray(colour, np.float32) * shade[:, None]
    return best_t, pid, col


def _people_at(frame: int, n_frames: int, n_people: int, laps: float = 1.0):
    out = []
    for k in range(n_people):
        pos, heading = person_pose(k, frame, n_frames, laps)
        ch, sh = np.cos(heading), np.sin(heading)
        Rb = np.array([[ch, -sh, 0], [sh, ch, 0], [0, 0, 1.0]])
        swing = 0.25 * np.sin(frame * 0.6 + k)
        ell = []
        for i, (c, r, slot) in enumerate(_PARTS):
            c = np.array(c, dtype=np.float64)
            if i >= 5:  # legs swing forward/back
                c = c + np.array([0, swing * (1 if i == 5 else -1) * 0.5, 0])
            centre = np.array([pos[0], pos[1], 0.0]) + Rb @ c
            ell.append((centre, Rb, np.array(r), _OUTFITS[k % len(_OUTFITS)][slot]))
        out.append(ell)
    return out


def away_camera(size=(320, 240), f: float = 300.0) -> Camera:
    """A camera near the wall looking at it, away from where people walk: it sees no one."""
    w, h = size
    C = np.array([7.5, 0.0, 1.5])
    z = np.array([1.0, 0.0, 0.0])
    x = np.cross(z, [0, 0, 1.0])
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Camera.create("away", [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], [], R, -R @ C, w, h)


def make_scene(
    root: Path,
    n_people: int = 1,
    n_frames: int = 30,
    n_cams: int = 4,
    size=(320, 240),
    distort: bool = True,
    noise: float = 2.0,
    seed: int = 0,
    codec: str = "mp4v",
    present: tuple[int, int] | None = None,
    with_away_camera: bool = False,
    laps: float = 1.0,
) -> SynthScene:
    """Render a scene into `root` (videos, truth masks) and return its description.

    present: (first, last) frame in which people are in the scene (default all frames).
    with_away_camera: add a camera that looks away from everyone.
    """
    root = Path(root)
    (root / "videos").mkdir(parents=True, exist_ok=True)
    (root / "truth" / "masks").mkdir(parents=True, exist_ok=True)
    rig = ring_rig(n_cams, size=size, distort=distort)
    if with_away_camera:
        rig = Rig((*rig.cameras, away_camera(size)))
    rng = np.random.default_rng(seed)
    videos = {}
    first, last = present if present is not None else (0, n_frames - 1)
    people = [
        _people_at(f, n_frames, n_people, laps) if first <= f <= last else []
        for f in range(n_frames)
    ]
    for cam in rig:
        origin, d = _rays(cam)
        bg = _background(cam, origin, d)
        path = root / "videos" / f"{cam.name}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 25, size)
        if not writer.isOpened():
            raise RuntimeError(f"cannot write {path} with codec {codec}")
        masks = np.zeros((n_frames, size[1], size[0]), np.uint8)
        for f in range(n_frames):
            _, pid, col = _render_people(origin, d, people[f])
            img = np.where(pid[:, None] > 0, col, bg)
            img = img + rng.normal(0, noise, img.shape)
            writer.write(img.clip(0, 255).astype(np.uint8).reshape(size[1], size[0], 3))
            masks[f] = pid.reshape(size[1], size[0])
        writer.release()
        np.savez_compressed(root / "truth" / "masks" / f"{cam.name}.npz", masks=masks)
        videos[cam.name] = path
    return SynthScene(root, rig, videos, root / "truth", n_frames, n_people)


def make_short_scene(root: Path, with_away_camera: bool = False) -> SynthScene:
    """The short scene of the extraction tests: 12 frames, one person present only in frames
    3..8 (a few frames are empty); `with_away_camera` adds a camera that sees no one."""
    return make_scene(
        root,
        n_people=1,
        n_frames=12,
        present=(3, 8),
        with_away_camera=with_away_camera,
        seed=2,
        laps=0.4,
    )
