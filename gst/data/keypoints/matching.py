"""Which instances in which cameras are the same person: joint, cycle-consistent matching of 2D
landmarks across all calibrated views of one frame.

1. Pairs. For every two instances in two cameras, each body landmark seen confidently in both
   gives two viewing rays; their gap (metres, `geometry.ray_gaps`) is the symmetric epipolar
   distance measured at the person. The pair's cost is the confidence-weighted mean gap
   (truncated, so one wrong landmark cannot dominate), the better of the two left/right
   readings when `mirror` is on (detectors swap the sides of people seen from behind). Pairs
   whose rays meet behind a camera or outside the floor-to-ceiling range are impossible.
2. Proposals. Every pair cheaper than `pair_gap` is triangulated into a 3D skeleton and
   projected into all cameras; in each camera the instance it fits best (mean landmark error
   below `view_error` x the instance's size) supports it. This is where all cameras vote at
   once: two people who happen to line up in two views give a cheap pair, but its skeleton
   fits nobody in the other views.
3. Groups. The proposal with the most supporting cameras (then the smallest error) becomes a
   person; its skeleton is re-triangulated from all its views, views that do not fit are let
   go, and its instances leave the pool; repeat while proposals remain. A group holds at most
   one instance per camera and every instance joins at most one group, so the matching is
   cycle-consistent by construction (A~B and B~C put A, B, C in one group).
4. Leftovers. An instance that joined no group is tried against the 3D people that lack its
   camera (looser threshold: a half-hidden person's landmarks are poor); what still fits
   nobody is a single-view person and keeps its own group.

References: Dong et al., "Fast and Robust Multi-Person 3D Pose Estimation from Multiple Views"
(mvpose, CVPR 2019) for cycle-consistent multi-view matching; Pose2Sim for choosing views by
the reprojection error of triangulated keypoints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from calibration.camera import Camera, Rig
from gst.data.keypoints.geometry import project, ray_gaps, triangulate_weighted, viewing_rays
from gst.data.keypoints.instances import BODY_LANDMARKS, MIRROR, N_LANDMARKS, PersonInstance

_BODY = np.asarray(BODY_LANDMARKS)
# Mirror map restricted to the body landmarks (positions within _BODY).
_BODY_MIRROR = np.array([BODY_LANDMARKS.index(int(MIRROR[k])) for k in BODY_LANDMARKS])
FRONT_MARGIN = 0.2  # metres: people this far behind the front one are hidden by them
PRIOR_BONUS = 0.5  # a prior beats a pair that the same number of cameras fit
# a camera this high (m) above the world's origin along the rig's up, or lower: no floor at 0
MIN_CAMERA_HEIGHT = 0.1
# Bones whose length tells a real skeleton from one stitched from two people (metres; adult
# ranges with room for triangulation noise): shoulders, hips, upper arms, forearms, thighs,
# shins, shoulder to hip.
BONE_LIMITS = (
    ((11, 12), 0.18, 0.6),
    ((23, 24), 0.1, 0.5),
    ((11, 13), 0.15, 0.45),
    ((12, 14), 0.15, 0.45),
    ((13, 15), 0.12, 0.4),
    ((14, 16), 0.12, 0.4),
    ((23, 25), 0.25, 0.65),
    ((24, 26), 0.25, 0.65),
    ((25, 27), 0.25, 0.6),
    ((26, 28), 0.25, 0.6),
    ((11, 23), 0.3, 0.75),
    ((12, 24), 0.3, 0.75),
)


def implausible_bones(skeleton: np.ndarray) -> int:
    """How many of `BONE_LIMITS` a (33, 3) skeleton breaks (unknown bones do not count)."""
    bad = 0
    for (a, b), lo, hi in BONE_LIMITS:
        d = float(np.linalg.norm(skeleton[a] - skeleton[b]))
        bad += bool(np.isfinite(d) and not lo <= d <= hi)
    return bad


class AssociationError(ValueError):
    """The inputs to keypoint association are inconsistent (names the camera or setting)."""


@dataclass(frozen=True)
class MatchConfig:
    """Thresholds of keypoint association. Distances in metres, errors as a share of the size
    of the person in the image (the longer side of the instance's box)."""

    min_confidence: float = 0.3  # landmarks below this confidence are not used
    pair_gap: float = 0.12  # mean ray gap for a pair to propose a person
    gap_truncate: float = 0.5  # per-landmark gaps are capped at this
    min_shared: int = 5  # landmarks seen in both views for a pair to count
    view_error: float = 0.1  # mean landmark error for a camera's instance to join a person
    loose_error: float = 0.15  # attached without triangulating (half-hidden people)
    outlier_error: float = 0.15  # a view's landmark this far off is left out of triangulation
    # height range of a person's landmarks above the floor, along `up` (the rig's: `for_rig`);
    # None: not checked (a world whose floor is not at height 0)
    z_range: tuple[float, float] | None = (-0.5, 3.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    mirror: bool = True  # accept a view whose left and right sides are swapped
    max_bad_bones: int = 1  # a person whose skeleton breaks more bone limits is not kept
    min_front: float = 0.8  # share of a pair's landmarks that must meet in front of both cameras

    def for_rig(self, cameras: Sequence[Camera], up) -> tuple[MatchConfig, str | None]:
        """This config for a rig of `cameras` and up axis `up`: heights measured along `up`
        (z was taken as height whatever the rig's up: a y-up rig lost most pairs), and the
        height check left off, with the reason, where the world's floor is evidently not at
        height 0 (a camera at or below it, as in a world that is a camera's frame, or cameras
        that look at a point outside the height range, as over a floor at 3.6 m; every pair
        there fell outside the range)."""
        from calibration.checks import axes_meeting_point

        up = np.asarray(up, np.float64)
        up = tuple(float(x) for x in up / np.linalg.norm(up))
        if self.z_range is None:
            return replace(self, up=up), None
        heights = {c.name: float(c.center @ np.asarray(up)) for c in cameras}
        low = {n: h for n, h in heights.items() if h <= MIN_CAMERA_HEIGHT}
        why = None
        if low:
            name, h = min(low.items(), key=lambda kv: kv[1])
            why = f"camera {name} stands {h:.2f} m along the rig's up {up} from the world's origin"
        elif len(cameras) > 1:
            # where the cameras look: people, whose height a floor at 0 puts in the range
            aim = float(axes_meeting_point(list(cameras)) @ np.asarray(up))
            if not self.z_range[0] < aim < self.z_range[1]:
                why = f"the cameras look at a point {aim:.2f} m along the rig's up {up}"
        if why is None:
            return replace(self, up=up), None
        why += ": the floor is not at height 0 there, so people's heights are not checked"
        return replace(self, up=up, z_range=None), why

    def __post_init__(self):
        for name in ("pair_gap", "gap_truncate", "view_error", "loose_error", "outlier_error"):
            if not getattr(self, name) > 0:
                raise AssociationError(f"MatchConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.min_confidence < 1:
            raise AssociationError(
                f"MatchConfig.min_confidence must be in [0, 1), got {self.min_confidence}"
            )
        if not 0 <= self.min_front <= 1:  # NaN too: it never found a pair impossible
            raise AssociationError(f"MatchConfig.min_front must be in [0, 1], got {self.min_front}")
        if self.min_shared < 2:
            raise AssociationError(f"MatchConfig.min_shared must be >= 2, got {self.min_shared}")


@dataclass(frozen=True)
class PersonGroup:
    """One person in one frame: their instance in each camera that sees them."""

    views: dict[str, int]  # camera -> index of the instance in that camera's list
    skeleton: np.ndarray | None  # (33, 3) world landmarks, NaN where not triangulated
    errors: dict[str, float]  # camera -> mean landmark error against the skeleton (share)
    mirrored: dict[str, bool]  # camera -> that view's left and right were swapped
    loose: tuple[str, ...] = ()  # cameras attached by the loose test (not triangulated)

    @property
    def single_view(self) -> bool:
        return len(self.views) == 1

    @property
    def centre(self) -> np.ndarray | None:
        """Mean of the triangulated body landmarks (world), None if there are none."""
        if self.skeleton is None:
            return None
        pts = self.skeleton[_BODY]
        ok = np.all(np.isfinite(pts), axis=1)
        return pts[ok].mean(axis=0) if ok.any() else None


@dataclass(frozen=True)
class FrameMatch:
    """All people of one frame; every instance of every camera is in exactly one group."""

    groups: list[PersonGroup]
    notes: list[str] = field(default_factory=list)  # skipped cameras, instances with no landmarks

    def group_of(self, camera: str, index: int) -> int | None:
        for g, group in enumerate(self.groups):
            if group.views.get(camera) == index:
                return g
        return None


@dataclass
class CameraView:
    """Per-camera arrays of the instances (body landmarks only)."""

    cam: Camera
    xy: np.ndarray  # (n, B, 2) distorted pixels
    conf: np.ndarray  # (n, B) confidence, 0 below the threshold
    rays: np.ndarray  # (n, B, 3)
    scale: np.ndarray  # (n,) person size in pixels
    full: np.ndarray  # (n, 33, 3) all landmarks: u, v, confidence (0 below the threshold)


def camera_view(cam: Camera, instances: Sequence[PersonInstance], min_conf: float) -> CameraView:
    n = len(instances)
    lm = np.stack([i.landmarks[_BODY] for i in instances]) if n else np.zeros((0, len(_BODY), 3))
    conf = np.where(lm[..., 2] >= max(min_conf, 1e-9), lm[..., 2], 0.0)
    scale = np.array([i.scale for i in instances], dtype=np.float64)
    # A box-less instance: size from its landmarks.
    for k in np.flatnonzero(~(scale > 0)):
        seen = conf[k] > 0
        span = np.ptp(lm[k, seen, :2], axis=0) if seen.sum() >= 2 else np.zeros(2)
        scale[k] = max(float(span.max()), 1.0)
    full = (
        np.stack([i.landmarks for i in instances]) if n else np.zeros((0, N_LANDMARKS, 3))
    ).copy()
    full[..., 2] = np.where(full[..., 2] >= max(min_conf, 1e-9), full[..., 2], 0.0)
    # a landmark beyond where the lens model inverts has no ray (one hundreds of px off was
    # matched against other cameras): unseen, with a finite stand-in (0 x NaN is NaN)
    rays = viewing_rays(cam, lm[..., :2], exact_only=True)
    lost = ~np.isfinite(rays).all(-1) & (conf > 0)
    conf = np.where(lost, 0.0, conf)
    rays = np.where(np.isfinite(rays), rays, cam.R[2])
    return CameraView(cam, lm[..., :2], conf, rays, scale, full)


def pair_costs(a: CameraView, b: CameraView, config: MatchConfig) -> tuple[np.ndarray, np.ndarray]:
    """(na, nb) mean ray gap in metres (NaN: too few shared landmarks; inf: impossible) and
    (na, nb) bool: whether b's instance reads better mirrored."""
    na, nb = len(a.xy), len(b.xy)
    flip = np.zeros((na, nb), bool)
    if na == 0 or nb == 0:
        return np.full((na, nb), np.nan), flip
    ca, cb = a.cam.center, b.cam.center
    zlo, zhi = config.z_range or (-np.inf, np.inf)
    up = np.asarray(config.up, np.float64)
    readings = [np.arange(len(_BODY))] + ([_BODY_MIRROR] if config.mirror else [])
    costs = []
    for order in readings:
        rb, wb = b.rays[:, order], b.conf[:, order]
        gap, mid, s, t = ray_gaps(ca, a.rays[:, None], cb, rb[None])  # (na, nb, B)
        w = np.minimum(a.conf[:, None], wb[None])
        n_seen = (w > 0).sum(axis=-1)
        height = mid @ up
        ok = (s > 0.05) & (t > 0.05) & (height > zlo) & (height < zhi)
        wsum = np.maximum(w.sum(axis=-1), 1e-12)
        front = (w * ok).sum(axis=-1) / wsum
        mean_gap = (w * np.minimum(gap, config.gap_truncate)).sum(axis=-1) / wsum
        c = np.where(n_seen < config.min_shared, np.nan, mean_gap)
        costs.append(
            np.where((n_seen >= config.min_shared) & (front < config.min_front), np.inf, c)
        )
    cost = costs[0]
    if config.mirror:
        flip = np.isfinite(costs[1]) & ~(costs[0] <= costs[1])
        cost = np.where(flip, costs[1], costs[0])
    return cost, flip


def fit_errors(
    skeletons: np.ndarray, view: CameraView, config: MatchConfig, truncate: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Mean landmark error (share of each instance's size) of P body skeletons (P, B, 3) against
    the n instances of one camera: (P, n) errors (inf: fewer than `min_shared` landmarks to
    compare) and (P, n) bool: the instance reads better mirrored."""
    P, n = len(skeletons), len(view.xy)
    if P == 0 or n == 0:
        return np.full((P, n), np.inf), np.zeros((P, n), bool)
    uv, _ = project(view.cam, skeletons.reshape(-1, 3))
    uv = uv.reshape(P, 1, -1, 2)
    okp = np.all(np.isfinite(uv), axis=-1)  # (P, 1, B)
    best = np.full((P, n), np.inf)
    flip = np.zeros((P, n), bool)
    for mirrored, order in [(False, np.arange(len(_BODY)))] + (
        [(True, _BODY_MIRROR)] if config.mirror else []
    ):
        xy, w = view.xy[None, :, order], view.conf[None, :, order]  # (1, n, B, .)
        w = np.where(okp, w, 0.0)
        d = np.linalg.norm(np.nan_to_num(uv) - xy, axis=-1) / view.scale[None, :, None]
        wsum = w.sum(axis=-1)
        e = (w * np.minimum(d, truncate)).sum(axis=-1) / np.maximum(wsum, 1e-12)
        e = np.where((w > 0).sum(axis=-1) >= config.min_shared, e, np.inf)
        better = e < best
        best = np.where(better, e, best)
        flip = np.where(better, mirrored, flip)
    return best, flip


def _oriented(view: CameraView, k: int, mirrored: bool) -> tuple[np.ndarray, np.ndarray]:
    order = _BODY_MIRROR if mirrored else np.arange(len(_BODY))
    return view.xy[k, order], view.conf[k, order]


def _triangulate_rejecting(
    views: dict[str, CameraView],
    members: dict[str, tuple[int, bool]],
    xy: np.ndarray,
    w: np.ndarray,
    config: MatchConfig,
) -> np.ndarray:
    """Weighted triangulation of the members' (V, L, 2) landmarks `xy`, weights `w` (V, L);
    a view's landmark farther than `config.outlier_error` (in the person's scale) from the
    first estimate is left out and the point solved again (the first estimate where that fails)."""
    names = list(members)
    cams = [views[n].cam for n in names]
    w = w.copy()
    X = triangulate_weighted(cams, xy, w)
    for v, n in enumerate(names):
        uv, _ = project(cams[v], X)
        err = np.linalg.norm(uv - xy[v], axis=-1) / views[n].scale[members[n][0]]
        w[v, ~(err <= config.outlier_error)] = 0.0
    X2 = triangulate_weighted(cams, xy, w)
    return np.where(np.isfinite(X2), X2, X)


def _triangulate_group(
    views: dict[str, CameraView], members: dict[str, tuple[int, bool]], config: MatchConfig
) -> np.ndarray:
    """(B, 3) body landmarks from the group's views; a view's landmark far from the first
    estimate is left out and the point solved again."""
    xy = np.stack([_oriented(views[n], *members[n])[0] for n in members])
    w = np.stack([_oriented(views[n], *members[n])[1] for n in members])
    return _triangulate_rejecting(views, members, xy, w, config)


def _triangulate_all(
    views: dict[str, CameraView], members: dict[str, tuple[int, bool]], config: MatchConfig
) -> np.ndarray:
    """(33, 3) world landmarks of a group from all 33 of each view's landmarks (mirrored views
    read mirrored), with the same outlier rejection as `_triangulate_group`."""
    lm = np.stack(
        [views[n].full[k][MIRROR] if fl else views[n].full[k] for n, (k, fl) in members.items()]
    )
    return _triangulate_rejecting(views, members, lm[..., :2], lm[..., 2], config)


def _full_skeleton(body: np.ndarray) -> np.ndarray:
    out = np.full((N_LANDMARKS, 3), np.nan)
    out[_BODY] = body
    return out


def match_frame(
    instances: Mapping[str, Sequence[PersonInstance]],
    rig: Rig | Sequence[Camera],
    config: MatchConfig = MatchConfig(),
    priors: Sequence[np.ndarray] = (),
) -> FrameMatch:
    """Group the person instances of one frame (camera name -> instances) into people.

    Every instance ends in exactly one group; a group holds at most one instance per camera.
    Cameras in `instances` must be in the rig; cameras with no instances are fine. `priors` are
    (33, 3) world skeletons where people are expected (e.g. `PersonIdTracker.predict`): they
    are proposals like the pairs, preferred among proposals that as many cameras fit.
    """
    cams = {c.name: c for c in (rig.cameras if isinstance(rig, Rig) else rig)}
    if isinstance(rig, Rig):  # heights along the rig's own up (CrowdTracker passes cameras)
        config, _why = config.for_rig(rig.cameras, rig.up)
    unknown = sorted(set(instances) - set(cams))
    if unknown:
        raise AssociationError(
            f"instances given for camera(s) {unknown} that are not in the rig {sorted(cams)}"
        )
    notes = []
    names = [n for n in cams if n in instances and len(instances[n])]
    views = {n: camera_view(cams[n], list(instances[n]), config.min_confidence) for n in names}
    for n in cams:
        if n in instances and not len(instances[n]):
            notes.append(f"camera {n}: nobody found")
    for n in names:
        for k in np.flatnonzero((views[n].conf > 0).sum(axis=1) < config.min_shared):
            notes.append(
                f"camera {n}, instance {k}: fewer than {config.min_shared} confident landmarks"
            )

    # 1-2. Proposals: the priors (e.g. the people of the previous frames, moved on), then every
    # cheap pair triangulated from its two views. A proposal fixes some instances (the pair's).
    fixed: list[dict[str, tuple[int, bool]]] = []
    skel, rank = [], []
    for i, prior in enumerate(priors):
        prior = np.asarray(prior, np.float64)
        if prior.size != N_LANDMARKS * 3:  # reshape's own error named neither prior nor shape
            raise AssociationError(
                f"prior {i} has shape {prior.shape}, expected ({N_LANDMARKS}, 3) world landmarks"
            )
        body = prior.reshape(N_LANDMARKS, 3)[_BODY]
        if np.count_nonzero(np.all(np.isfinite(body), axis=1)) >= config.min_shared:
            fixed.append({})
            skel.append(body)
            rank.append(-PRIOR_BONUS)
    for ia, na in enumerate(names):
        for nb in names[ia + 1 :]:
            cost, flip = pair_costs(views[na], views[nb], config)
            for i, j in zip(*np.nonzero(cost < config.pair_gap), strict=True):
                fl = bool(flip[i, j])
                fixed.append({na: (int(i), False), nb: (int(j), fl)})
                skel.append(
                    triangulate_weighted(
                        [views[na].cam, views[nb].cam],
                        np.stack([views[na].xy[i], _oriented(views[nb], j, fl)[0]]),
                        np.stack([views[na].conf[i], _oriented(views[nb], j, fl)[1]]),
                    )
                )
                rank.append(0.45 * float(cost[i, j]) / config.pair_gap)
    n_prop = len(fixed)
    skel_arr = np.stack(skel) if skel else np.zeros((0, len(_BODY), 3))
    fit = {n: fit_errors(skel_arr, views[n], config) for n in names}  # (P, n_c) each
    in_fixed = {n: np.array([n in fx for fx in fixed], bool) for n in names}
    rank_arr = np.asarray(rank, np.float64)

    # 3. Greedy discovery of people by support: the proposal that most cameras fit first.
    used = {n: np.zeros(len(views[n].xy), bool) for n in names}
    found: list[dict[str, tuple[int, bool]]] = []
    alive = np.ones(n_prop, bool)
    while True:
        for p in np.flatnonzero(alive):
            if any(used[n][k] for n, (k, _) in fixed[p].items()):
                alive[p] = False
        if not alive.any():
            break
        support = np.array([len(fx) for fx in fixed], np.float64)
        err_sum = np.zeros(n_prop)
        pick = {}
        for n in names:
            e = np.where(used[n][None], np.inf, fit[n][0])
            k = e.argmin(axis=1)
            ek = e[np.arange(n_prop), k]
            ok = (ek < config.view_error) & ~in_fixed[n]
            support += ok
            err_sum += np.where(ok, ek, 0.0)
            pick[n] = (k, ok)
        mean_err = err_sum / np.maximum(support, 1)
        # Most cameras first; among equals priors, then the smallest errors (tie-break < 1).
        key = np.where(alive, support - 0.45 * mean_err / config.view_error - rank_arr, -np.inf)
        p = int(np.argmax(key))
        alive[p] = False
        members = dict(fixed[p])
        for n in names:
            k, ok = pick[n]
            if ok[p]:
                members[n] = (int(k[p]), bool(fit[n][1][p, k[p]]))
        if len(members) < 2:
            continue
        group = _grow(views, names, used, members, config)
        if group is None:
            continue
        for n, (k, _) in group.items():
            used[n][k] = True
        found.append(group)

    # 4. All people at once, per camera: each instance to the person it fits (the nearest one
    # when several fit: the detector sees whoever is in front), then triangulate again.
    groups = _assign(views, names, found, config)
    assigned = {n: np.zeros(len(views[n].xy), bool) for n in names}
    for g in groups:
        for n, k in g.views.items():
            assigned[n][k] = True
    for n in names:
        for k in np.flatnonzero(~assigned[n]):
            groups.append(PersonGroup({n: int(k)}, None, {}, {n: False}))
    return FrameMatch(groups, notes)


def _grow(
    views: dict[str, CameraView],
    names: list[str],
    used: dict[str, np.ndarray],
    members: dict[str, tuple[int, bool]],
    config: MatchConfig,
) -> dict[str, tuple[int, bool]] | None:
    """Re-triangulate a proposal from all its views, then take in each camera the free instance
    that fits the new skeleton best (twice); None if fewer than two views still fit."""
    for _ in range(2):
        body = _triangulate_group(views, members, config)
        new: dict[str, tuple[int, bool]] = {}
        for n in names:
            e, f = fit_errors(body[None], views[n], config)
            e = np.where(used[n], np.inf, e[0])
            k = int(np.argmin(e))
            if e[k] < config.view_error:
                new[n] = (k, bool(f[0, k]))
        if len(new) < 2:
            return None
        if new == members:
            break
        members = new
    body = _triangulate_group(views, members, config)
    if implausible_bones(_full_skeleton(body)) > config.max_bad_bones:
        return None
    return members


def _depths(cam: Camera, bodies: np.ndarray) -> np.ndarray:
    """(G,) camera depth of the centre of each (G, B, 3) body (inf where unknown)."""
    out = np.full(len(bodies), np.inf)
    for g, body in enumerate(bodies):
        ok = np.all(np.isfinite(body), axis=1)
        if ok.any():
            out[g] = cam.to_camera(body[ok].mean(axis=0)[None])[0, 2]
    return out


def _assign(
    views: dict[str, CameraView],
    names: list[str],
    found: list[dict[str, tuple[int, bool]]],
    config: MatchConfig,
    rounds: int = 2,
) -> list[PersonGroup]:
    """Per camera, Hungarian between the people found and that camera's instances by landmark
    error; an instance that several people fit goes to the nearest of them (people more than
    `FRONT_MARGIN` behind the front one pay `view_error`). Views fitting below `view_error` are
    triangulated, those below `loose_error` only attached. Repeated `rounds` times with the new
    skeletons; a person left with fewer than two triangulated views is dissolved."""
    members = [dict(m) for m in found]
    bodies = np.stack([_triangulate_group(views, m, config) for m in members]) if members else None
    loose: list[dict[str, tuple[int, bool, float]]] = [{} for _ in members]
    errors: list[dict[str, float]] = [{} for _ in members]
    for _ in range(rounds):
        if not members:
            break
        new = [{} for _ in members]
        loose = [{} for _ in members]
        errors = [{} for _ in members]
        for n in names:
            e, f = fit_errors(bodies, views[n], config)  # (G, n)
            z = _depths(views[n].cam, bodies)
            fits = e < config.view_error
            front = np.where(fits, z[:, None], np.inf).min(axis=0)  # (n,)
            behind = z[:, None] > front[None] + FRONT_MARGIN
            cost = e + np.where(behind & fits, config.view_error, 0.0)
            cost = np.where(e < config.loose_error, cost, 1e6)
            rows, cols = linear_sum_assignment(cost)
            for g, k in zip(rows, cols, strict=True):
                if cost[g, k] >= 1e6:
                    continue
                errors[g][n] = float(e[g, k])
                if e[g, k] < config.view_error:
                    new[g][n] = (int(k), bool(f[g, k]))
                else:
                    loose[g][n] = (int(k), bool(f[g, k]), float(e[g, k]))
        keep = [
            g
            for g in range(len(members))
            if len(new[g]) >= 2
            and implausible_bones(_full_skeleton(_triangulate_group(views, new[g], config)))
            <= config.max_bad_bones
        ]
        members = [new[g] for g in keep]
        loose = [loose[g] for g in keep]
        errors = [errors[g] for g in keep]
        bodies = (
            np.stack([_triangulate_group(views, m, config) for m in members]) if members else None
        )
    out = []
    for g, m in enumerate(members):
        body = _triangulate_all(views, m, config)
        mirrored = {n: fl for n, (_, fl) in m.items()} | {
            n: fl for n, (_, fl, _) in loose[g].items()
        }
        # The majority reading defines left and right (a mirrored proposal flips them all).
        if sum(mirrored.values()) * 2 > len(mirrored):
            mirrored = {n: not fl for n, fl in mirrored.items()}
            body = body[MIRROR]
        out.append(
            PersonGroup(
                {n: k for n, (k, _) in m.items()} | {n: k for n, (k, _, _) in loose[g].items()},
                body,
                errors[g],
                mirrored,
                tuple(loose[g]),
            )
        )
    return out
