"""Which person each foreground pixel belongs to, from the people's skeletons.

Each person is a set of capsules between landmarks (limbs, torso, head) with body-part radii
in metres. Projected into a camera, a capsule covers the pixels within its radius of its axis
(the radius in pixels shrinks with depth). A foreground pixel goes to:

- the person nearest the camera among those whose capsules cover it (a player in front hides
  the one behind), when any do;
- otherwise the person whose capsules are nearest in units of their radii (a pixel between
  two arms goes to the arm it is closest to relative to its thickness).

People known only in 2D (seen by one camera) have capsules drawn from their 2D landmarks with
a radius in pixels and rank behind every 3D person where capsules overlap.

The same pass tells how much of each person is hidden: the share of their capsule pixels where
someone else is in front (their visibility in that camera).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration.camera import Camera
from gst.data.keypoints.geometry import project

# (end a, end b, radius in metres). An end is a landmark index or a tuple (their mean).
_SH, _HIP = (11, 12), (23, 24)
_HEAD = (7, 8)
CAPSULES: tuple[tuple[int | tuple[int, ...], int | tuple[int, ...], float], ...] = (
    (_SH, _HIP, 0.13),  # torso core
    (11, 23, 0.09),
    (12, 24, 0.09),
    (11, 12, 0.07),
    (23, 24, 0.09),
    (_SH, _HEAD, 0.06),  # neck
    (_HEAD, _HEAD, 0.11),  # head (a sphere)
    (11, 13, 0.055),
    (13, 15, 0.045),
    (15, (17, 19, 21), 0.045),
    (12, 14, 0.055),
    (14, 16, 0.045),
    (16, (18, 20, 22), 0.045),
    (23, 25, 0.08),
    (25, 27, 0.06),
    (27, 29, 0.045),
    (29, 31, 0.045),
    (24, 26, 0.08),
    (26, 28, 0.06),
    (28, 30, 0.045),
    (30, 32, 0.045),
)


@dataclass(frozen=True)
class OwnershipConfig:
    radius_scale: float = 0.8  # capsule radii x this (thinner than the body: a capsule that
    # bulges past a silhouette would take the pixels of the person behind it)
    reach: float = 3.0  # foreground further than this many radii from everyone is nobody's
    pixel_radius: float = 0.04  # capsule radius of 2D-only people, share of their box's longer side
    # The capsule fields are evaluated on every `step`-th pixel of each axis (the centre of each
    # step x step block) and each block's pixels take its owner; the foreground stays at full
    # resolution. 1: every pixel. On the lab capture 2 is 2.9x faster and gives the same crops
    # and ids (docs/extract.md, "Speed").
    step: int = 2

    def __post_init__(self):
        if not (self.radius_scale > 0 and self.reach >= 1 and self.pixel_radius > 0):
            raise ValueError(
                "OwnershipConfig needs radius_scale > 0, reach >= 1 and pixel_radius > 0, got "
                f"{self.radius_scale}, {self.reach}, {self.pixel_radius}"
            )
        if self.step < 1:
            raise ValueError(f"OwnershipConfig step must be >= 1, got {self.step}")


def _end_groups() -> list[tuple[np.ndarray, np.ndarray]]:
    """The capsule ends of CAPSULES grouped by how many landmarks they average: per group the
    ends' flat positions (capsule * 2 + end) and their (K, m) landmark indices."""
    ends = [e if isinstance(e, tuple) else (e,) for a, b, _ in CAPSULES for e in (a, b)]
    sizes = sorted({len(e) for e in ends})
    return [
        (
            np.array([i for i, e in enumerate(ends) if len(e) == m]),
            np.array([e for e in ends if len(e) == m]),
        )
        for m in sizes
    ]


_END_GROUPS = _end_groups()
_RADII = np.array([r for _, _, r in CAPSULES])


def capsules(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Capsule ends (S, 2, D) and radii (S,) of a (33, D) skeleton (metres for 3D), and the
    (S,) bool of capsules whose ends are known (finite). An end that names several landmarks
    is their mean."""
    flat = np.empty((2 * len(CAPSULES), points.shape[1]))
    for where, index in _END_GROUPS:
        flat[where] = points[index].mean(axis=1)
    ends = flat.reshape(len(CAPSULES), 2, -1)
    return ends, _RADII.copy(), np.all(np.isfinite(ends), axis=(1, 2))


@dataclass(frozen=True)
class Ownership:
    labels: np.ndarray  # (H, W) int32: person index + 1, 0 = nobody
    visibility: np.ndarray  # (P,) share of each person's capsule pixels not hidden by others
    area: np.ndarray  # (P,) capsule pixels of each person in the image
    alone: np.ndarray  # (P,) bool: no one else's capsules overlap this person's in the image
    # (H, W) int32: person index + 1 of the front capsule covering each foreground pixel, 0
    # where no capsule covers it (pixels `labels` gives by nearness alone are 0 here); None
    # unless asked for (`own_pixels(with_covered=True)`: a second full image, on the hot path)
    covered: np.ndarray | None = None


def _rasterize(
    seg: tuple, xs: np.ndarray, ys: np.ndarray, reach: float, Q: np.ndarray, Z: np.ndarray
) -> None:
    """One person's fields on the grid of pixel coordinates `xs` x `ys` (increasing), written
    into `Q` and `Z` (len(ys), len(xs), filled with inf): per sample the smallest
    distance/radius over their capsules (ends a, b (S, 2), radii ra, rb at the ends in pixels,
    depths za, zb), and the depth of the front covering capsule (inf where none covers). Each
    capsule is evaluated only over its own box grown by `reach` radii, in float32 with
    in-place arithmetic (the grid is large, the capsules many)."""
    a, b, ra, rb, za, zb = seg
    grow = reach * np.maximum(ra, rb)
    lo = np.minimum(a, b) - grow[:, None] - 1
    hi = np.maximum(a, b) + grow[:, None] + 1
    cx0, cx1 = np.searchsorted(xs, lo[:, 0]), np.searchsorted(xs, hi[:, 0], side="right")
    cy0, cy1 = np.searchsorted(ys, lo[:, 1]), np.searchsorted(ys, hi[:, 1], side="right")
    f32 = np.float32
    for i in range(len(a)):
        if cx1[i] <= cx0[i] or cy1[i] <= cy0[i]:
            continue
        px = xs[cx0[i] : cx1[i]] - f32(a[i, 0])
        py = (ys[cy0[i] : cy1[i]] - f32(a[i, 1]))[:, None]
        abx, aby = f32(b[i, 0] - a[i, 0]), f32(b[i, 1] - a[i, 1])
        l2 = f32(max(float(abx) ** 2 + float(aby) ** 2, 1e-9))
        t = py * (aby / l2) + px * (abx / l2)
        np.clip(t, 0.0, 1.0, out=t)
        dx = px - t * abx
        dy = py - t * aby
        dx *= dx
        dy *= dy
        dx += dy
        np.sqrt(dx, out=dx)  # distance to the axis
        if ra[i] == rb[i]:
            dx /= f32(max(ra[i], 1e-6))
        else:
            r = t * f32(rb[i] - ra[i])
            r += f32(ra[i])
            np.maximum(r, f32(1e-6), out=r)
            dx /= r
        sq, sz = Q[cy0[i] : cy1[i], cx0[i] : cx1[i]], Z[cy0[i] : cy1[i], cx0[i] : cx1[i]]
        np.minimum(sq, dx, out=sq)
        if za[i] == zb[i]:
            np.putmask(sz, (dx < 1.0) & (sz > f32(za[i])), f32(za[i]))
        else:
            t *= f32(zb[i] - za[i])
            t += f32(za[i])
            np.minimum(sz, np.where(dx < 1.0, t, np.inf), out=sz)


def _sane(seg, W: int, H: int):
    """Keep the capsules that are numbers and lie near the image (a skeleton reaching around a
    camera projects to huge coordinates); None when none is left."""
    if seg is None:
        return None
    a, b, ra, rb, za, zb = seg
    ok = np.all(np.isfinite(np.c_[a, b, ra, rb]), axis=1) & (ra > 0) & (rb > 0)
    lim = 2.0 * max(W, H)
    ok &= np.all((np.c_[a, b] > -lim) & (np.c_[a, b] < lim + max(W, H)), axis=1)
    if not ok.any():
        return None
    return a[ok], b[ok], ra[ok], rb[ok], za[ok], zb[ok]


def _min_first(fields: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum over axis 0 of (n, H, W) and its first index (`argmin`'s answer, without its slow
    strided pass over a short first axis)."""
    low, index = fields[0].copy(), np.zeros(fields.shape[1:], np.intp)
    for k in range(1, len(fields)):
        better = fields[k] < low
        index[better] = k
        np.minimum(low, fields[k], out=low)
    return low, index


def own_pixels(
    cam: Camera,
    foreground: np.ndarray,
    skeletons: Sequence[np.ndarray | None],
    landmarks2d: Sequence[np.ndarray | None] = (),
    config: OwnershipConfig = OwnershipConfig(),
    scale: float = 1.0,
    with_covered: bool = False,
) -> Ownership:
    """Person labels of the `foreground` (H, W) bool pixels of one camera.

    `skeletons[k]` is person k's (33, 3) world landmarks (NaN where unknown) or None; for a
    person without a skeleton, `landmarks2d[k]` gives (33, 3) u, v, confidence in this camera's
    distorted pixels. `scale` maps full-resolution pixels to the foreground's resolution (e.g.
    0.5 for a half-size work image). `with_covered`: also `Ownership.covered`.
    """
    H, W = foreground.shape
    n = len(skeletons)
    segs = []  # per person: (a, b, ra, rb, za, zb) in foreground pixels
    for k in range(n):
        sk = skeletons[k]
        if sk is not None:
            ends, radii, ok = capsules(np.asarray(sk, np.float64))
            ends, radii = ends[ok], radii[ok] * config.radius_scale
            if not len(ends):
                segs.append(None)
                continue
            flat = ends.reshape(-1, 3)
            uv, front = project(cam, flat)
            z = cam.to_camera(flat)[:, 2]
            good = front.reshape(-1, 2).all(axis=1)
            # full-resolution pixel centres to the work image's ((u + 0.5) s - 0.5)
            uv, z = (uv.reshape(-1, 2, 2)[good] + 0.5) * scale - 0.5, z.reshape(-1, 2)[good]
            r_px = radii[good, None] * cam.fx * scale / z
            segs.append(
                (
                    uv[:, 0],
                    uv[:, 1],
                    r_px[:, 0],
                    r_px[:, 1],
                    z[:, 0] - radii[good],
                    z[:, 1] - radii[good],
                )
            )
        elif k < len(landmarks2d) and landmarks2d[k] is not None:
            lm = np.asarray(landmarks2d[k], np.float64)
            pts = np.where(lm[:, 2:3] > 0, lm[:, :2], np.nan)
            ends, radii, ok = capsules(pts)
            ends = (ends[ok] + 0.5) * scale - 0.5
            seen = lm[lm[:, 2] > 0, :2]
            size = float(np.ptp(seen, axis=0).max()) if len(seen) >= 2 else 0.0
            r = np.full(len(ends), config.pixel_radius * size * scale)
            far = np.full(len(ends), 1e9)  # behind every 3D person
            segs.append((ends[:, 0], ends[:, 1], r, r, far, far) if len(ends) else None)
        else:
            segs.append(None)
    segs = [_sane(seg, W, H) for seg in segs]
    labels = np.zeros((H, W), np.int32)
    visibility, area = np.zeros(n), np.zeros(n)
    live = [k for k in range(n) if segs[k] is not None]
    if not live:
        return Ownership(
            labels, visibility, area, np.ones(n, bool), labels.copy() if with_covered else None
        )
    # Work on the pixels near someone: the union of the capsules' boxes grown by `reach`.
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for k in live:
        a, b, ra, rb = segs[k][:4]
        rr = config.reach * np.maximum(ra, rb)[:, None]
        lo = np.minimum(lo, np.minimum(a - rr, b - rr).min(axis=0))
        hi = np.maximum(hi, np.maximum(a + rr, b + rr).max(axis=0))
    x0, y0 = (max(0, int(np.floor(v))) for v in lo)
    x1, y1 = min(W, int(np.ceil(hi[0])) + 1), min(H, int(np.ceil(hi[1])) + 1)
    if x1 <= x0 or y1 <= y0:
        return Ownership(
            labels, visibility, area, np.ones(n, bool), labels.copy() if with_covered else None
        )

    # Samples at the centres of step x step blocks from (x0, y0); a block's pixels share them.
    st = config.step
    xs = (np.arange(x0, x1, st) + (st - 1) / 2).astype(np.float32)
    ys = (np.arange(y0, y1, st) + (st - 1) / 2).astype(np.float32)
    Q = np.full((n, len(ys), len(xs)), np.inf, np.float32)
    Z = np.full((n, len(ys), len(xs)), np.inf, np.float32)
    for k in live:
        _rasterize(segs[k], xs, ys, config.reach, Q[k], Z[k])
    covered = Q < 1.0
    # 2D-only people are behind every 3D person (depth 1e9); among people at the same depth
    # the nearer skeleton (smaller q) wins. (Z is finite exactly where a capsule covers.)
    tie = covered & (Z == _min_first(Z)[0][None])
    front = _min_first(np.where(tie, Q, np.inf))[1]
    q_min, nearest = _min_first(Q)
    any_cover = covered.any(axis=0)
    owner = np.where(any_cover, front, nearest)
    near = np.where(q_min < config.reach, owner + 1, 0).astype(np.int32)
    fg = foreground[y0:y1, x0:x1]
    labels[y0:y1, x0:x1] = np.where(fg, _blocks(near, st, y1 - y0, x1 - x0), 0)
    cover_labels = None
    if with_covered:
        cover = np.where(any_cover, front + 1, 0).astype(np.int32)
        cover_labels = np.zeros((H, W), np.int32)
        cover_labels[y0:y1, x0:x1] = np.where(fg, _blocks(cover, st, y1 - y0, x1 - x0), 0)
    shared = np.count_nonzero(covered, axis=0) > 1
    alone = np.ones(n, bool)
    for k in live:
        samples = np.count_nonzero(covered[k])
        area[k] = samples * st * st
        visibility[k] = np.count_nonzero(covered[k] & (owner == k)) / samples if samples else 0.0
        alone[k] = not np.any(covered[k] & shared)
    return Ownership(labels, visibility, area, alone, cover_labels)


def _blocks(samples: np.ndarray, step: int, h: int, w: int) -> np.ndarray:
    """(h, w) pixels from samples at the centres of step x step blocks (each block's pixels
    take its sample)."""
    if step == 1:
        return samples
    sh, sw = samples.shape
    full = np.broadcast_to(samples[:, None, :, None], (sh, step, sw, step))
    return full.reshape(sh * step, sw * step)[:h, :w]
