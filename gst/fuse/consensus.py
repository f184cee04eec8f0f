"""Which views of a person-frame show that person: whole-skeleton consensus across cameras.

The extraction gives each crop a person id, and BlazePose finds one body per crop; where two
people overlap in a view, the crop's landmarks may belong to the other one (or to a bystander),
and a person seen from behind may have the left and right of a limb group exchanged. Both are
systematic for the whole view, so they are judged per view and skeleton, not per landmark:

1. hypotheses: for every pair of views of the frame, all landmarks are triangulated from those
   two views alone (confidence-weighted DLT);
2. each hypothesis scores the views that agree with it: a view agrees when the median distance
   between its landmarks and the projected hypothesis is below `agree` x the person's size in
   that view (the larger side of its landmarks' box); the hypothesis with the most agreeing
   views wins (ties: the smaller summed error);
3. the views that disagree with the winner are dropped for this person-frame (confidence 0),
   unless exchanging the left and right landmarks of one limb group (arms, legs, the head and
   torso) brings them within `agree`: then that group is exchanged.

With 6 cameras and two wrong views the winner is a pair of good views (4 agree against 2); a
frame where no pair gathers `min_agree` views is left as it is (the robust kernels of the
triangulation and the fit still apply).
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass, replace

import numpy as np

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.fuse.observations import PersonObservations
from gst.fuse.triangulate import TriangulationOptions, neighbour_mean, triangulate_points

__all__ = [
    "ConsensusOptions",
    "ConsensusReport",
    "view_consensus",
    "exchange_groups",
    "exchanges_against_body",
    "SWAP",
    "LIMB_GROUPS",
]

SWAP = BLAZEPOSE_MIRROR  # landmark index with left and right exchanged
LIMB_GROUPS: dict[str, tuple[int, ...]] = {
    "arms": tuple(range(13, 23)),  # elbows, wrists, fingers
    "legs": tuple(range(25, 33)),  # knees, ankles, heels, toes
    "torso": tuple(range(0, 13)) + (23, 24),  # face, shoulders, hips
}


@dataclass(frozen=True)
class ConsensusOptions:
    agree: float = 0.06  # a view agrees when its median landmark error < agree x person size
    min_agree: int = 3  # views a hypothesis needs before any view is dropped
    min_confidence: float = 0.3
    swap_gain: float = 0.5  # exchange a limb group when that scales its error by less than this
    # > 0: a second pass in which a pair hypothesis whose skeleton lies at the mean of the
    # first pass's winners at frames t - 1 and t + 1 scores this much more (less the farther,
    # median landmark distance; nothing from `temporal_radius_m` on): docs/fuse.md
    temporal_weight: float = 1.0
    temporal_radius_m: float = 0.15


@dataclass
class ConsensusReport:
    dropped: np.ndarray  # (T, C) bool: view dropped for this person-frame
    swapped: np.ndarray  # (T, C, 3) bool: limb group (arms, legs, torso) exchanged
    error: np.ndarray  # (T, C) median landmark error against the winning hypothesis, full px
    points: np.ndarray  # (T, M, 3) the winner triangulated from its agreeing views (NaN: none)
    agreeing: np.ndarray  # (T,) int: views that agreed with the winning pair


def _evidence(obs: PersonObservations, o: ConsensusOptions):
    """(T, C) views seen, (T, C, M, 2) landmarks with NaN as 0, and (T, C, M) their confidence,
    0 where missing, below `o.min_confidence` or in an unseen view."""
    seen = obs.rows >= 0
    conf = np.where(np.isfinite(obs.uv).all(-1), obs.confidence, 0.0)
    conf = np.where(conf >= o.min_confidence, conf, 0.0) * seen[..., None]
    return seen, np.nan_to_num(obs.uv), conf


def _view_errors(obs, X, uv, conf, min_conf):
    """Median error (..., C) of every view's landmarks against points X (..., M, 3), per limb
    group too (..., C, G), in full-image pixels."""
    P = obs.K @ obs.Rt  # (T, C, 3, 4)
    extra = X.ndim - 3  # hypothesis axes between T and M
    Pe = P.reshape(P.shape[:1] + (1,) * extra + P.shape[1:])
    Xh = np.concatenate([X, np.ones(X.shape[:-1] + (1,))], -1)
    q = np.einsum("t...cij,t...mj->t...cmi", Pe, Xh)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = q[..., :2] / q[..., 2:]
    uve = uv.reshape(uv.shape[:1] + (1,) * extra + uv.shape[1:])
    ok = (conf >= min_conf).reshape(conf.shape[:1] + (1,) * extra + conf.shape[1:])
    sc = obs.px_scale.reshape(obs.px_scale.shape[:1] + (1,) * extra + obs.px_scale.shape[1:])
    e = np.where(ok & (q[..., 2] > 0), np.linalg.norm(p - uve, axis=-1) * sc[..., None], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: unseen views
        whole = np.nanmedian(e, -1)
        groups = np.stack([np.nanmedian(e[..., list(g)], -1) for g in LIMB_GROUPS.values()], -1)
    return whole, groups


def _triangulate(obs, uv, conf, weights_cm):
    """Points (T, H, M, 3) triangulated with per-hypothesis view weights (T, H, C) x conf."""
    T, C, M = conf.shape
    H = weights_cm.shape[1]
    w = weights_cm[..., None] * conf[:, None]  # (T, H, C, M)

    def per_point(a):  # (T, C, ...) -> (T*H*M, C, ...)
        b = np.broadcast_to(a[:, None, None], (T, H, M) + a.shape[1:])
        return b.reshape((T * H * M,) + a.shape[1:])

    tri = triangulate_points(
        per_point(obs.K),
        per_point(obs.Rt),
        np.broadcast_to(np.moveaxis(uv, 1, 2)[:, None], (T, H, M, C, 2)).reshape(-1, C, 2),
        np.moveaxis(w, 2, 3).reshape(-1, C),
        per_point(obs.px_scale),
        TriangulationOptions(min_confidence=1e-6, max_rejections=0, refine_iterations=0),
    )
    return tri.points.reshape(T, H, M, 3)


def view_consensus(
    obs: PersonObservations, options: ConsensusOptions | None = None
) -> tuple[PersonObservations, ConsensusReport]:
    """A copy of `obs` with disagreeing views dropped and exchanged limb groups put right."""
    o = options or ConsensusOptions()
    T, C, M = obs.confidence.shape
    seen, uv, conf = _evidence(obs, o)
    pairs = np.array(list(itertools.combinations(range(C), 2)))  # (H, 2)
    report = ConsensusReport(
        np.zeros((T, C), bool), np.zeros((T, C, 3), bool), np.full((T, C), np.nan),
        np.full((T, M, 3), np.nan), np.zeros(T, int),
    )  # fmt: skip
    if len(pairs) == 0:
        return obs, report
    wpair = np.zeros((T, len(pairs), C))
    ok_pair = seen[:, pairs[:, 0]] & seen[:, pairs[:, 1]]  # (T, H)
    wpair[:, np.arange(len(pairs)), pairs[:, 0]] = 1.0
    wpair[:, np.arange(len(pairs)), pairs[:, 1]] = 1.0
    wpair *= ok_pair[..., None]
    Xh = _triangulate(obs, uv, conf, wpair)  # (T, H, M, 3)
    err, _ = _view_errors(obs, Xh, uv, conf, o.min_confidence)  # (T, H, C)
    limit = o.agree * _extent_px(obs, conf)  # (T, C)
    agree = (err < limit[:, None]) & seen[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):  # limit 0 (a view of no size): no
        # view agrees there, and only agreeing views' err / limit is used
        score = agree.sum(-1) - np.nansum(np.where(agree, err / limit[:, None], 0), -1) / (C + 1)
    score = np.where(ok_pair, score, -np.inf)
    best = score.argmax(1)
    if o.temporal_weight > 0 and T >= 3:
        first = _triangulate(obs, uv, conf, agree[np.arange(T), best].astype(float)[:, None])
        score = score + o.temporal_weight * _near_neighbours(Xh, first[:, 0], obs.frames, o)
        best = score.argmax(1)
    n_best = agree[np.arange(T), best].sum(-1)
    # refine the winner with all its agreeing views, then judge every view against it
    w_in = agree[np.arange(T), best].astype(float)[:, None]
    X = _triangulate(obs, uv, conf, w_in)[:, 0]
    err, grp = _view_errors(obs, X[:, None], uv, conf, o.min_confidence)
    err, grp = err[:, 0], grp[:, 0]
    sw_uv, sw_conf = uv[:, :, SWAP], conf[:, :, SWAP]
    _, grp_sw = _view_errors(obs, X[:, None], sw_uv, sw_conf, o.min_confidence)
    grp_sw = grp_sw[:, 0]
    decide = (n_best >= o.min_agree)[:, None] & seen
    # A limb group's left/right convention is the majority's: if the winning pair itself had
    # the group exchanged, more views agree exchanged than as they are; then the hypothesis is
    # mirrored for that group and the views that agreed with it as they are get exchanged.
    clear = decide[..., None] & (np.fmax(grp, grp_sw) > limit[..., None] / 2)
    want = clear & (grp_sw < o.swap_gain * grp)
    keep = clear & (grp < o.swap_gain * grp_sw)
    flip = want.sum(1) > keep.sum(1)  # (T, G)
    swap = np.where(flip[:, None], keep, want)
    for g, idx in enumerate(LIMB_GROUPS.values()):
        idx = np.array(idx)
        t = np.flatnonzero(flip[:, g])
        X[t[:, None], idx] = X[t[:, None], SWAP[idx]]
    fixed = exchange_groups(obs, swap)
    out_uv, out_conf = fixed.uv, fixed.confidence
    # errors after the exchanges decide the drops
    conf2 = np.where(np.isfinite(out_uv).all(-1), out_conf, 0.0)
    err2, _ = _view_errors(fixed, X[:, None], np.nan_to_num(out_uv), conf2, o.min_confidence)
    err2 = err2[:, 0]
    drop = decide & ~(err2 < limit)
    out_conf[drop] = 0.0
    X = np.where((n_best >= 2)[:, None, None], X, np.nan)
    report = ConsensusReport(drop, swap, err2, X, n_best)
    return replace(obs, uv=out_uv, confidence=out_conf), report


def _near_neighbours(Xh, first, frames, o: ConsensusOptions) -> np.ndarray:
    """(T, H) in [0, 1]: how near each hypothesis skeleton Xh (T, H, M, 3) lies to the mean of
    the winners `first` (T, M, 3) at the frames just before and after (consecutive frames
    only; 0 where either is missing), by the median distance over their common landmarks."""
    expected = neighbour_mean(first, np.asarray(frames))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: nothing to compare
        d = np.nanmedian(np.linalg.norm(Xh - expected[:, None], axis=-1), -1)
    return np.nan_to_num(np.clip(1 - d / o.temporal_radius_m, 0, 1))


def exchange_groups(obs: PersonObservations, swap: np.ndarray) -> PersonObservations:
    """A copy of `obs` with the left and right landmarks of each limb group exchanged where
    `swap` (T, C, G) is set (groups in LIMB_GROUPS order)."""
    out_uv, out_conf = obs.uv.copy(), obs.confidence.copy()
    for g, idx in enumerate(LIMB_GROUPS.values()):
        t, c = np.nonzero(swap[..., g])
        if len(t):
            idx = np.array(idx)
            out_uv[t[:, None], c[:, None], idx] = obs.uv[t[:, None], c[:, None], SWAP[idx]]
            out_conf[t[:, None], c[:, None], idx] = obs.confidence[
                t[:, None], c[:, None], SWAP[idx]
            ]
    return replace(obs, uv=out_uv, confidence=out_conf)


def exchanges_against_body(
    obs: PersonObservations, markers: np.ndarray, options: ConsensusOptions | None = None
) -> np.ndarray:
    """(T, C, G) bool: the limb groups of each view whose left and right landmarks lie much
    nearer the fitted body's opposite side (`markers` (T, M, 3) world, the body's landmark
    markers on `obs.frames`) than their own, by the consensus rule (the exchanged error below
    `swap_gain` x the error as detected, the larger of the two above half the agreement limit).

    The fitted body is a better judge than the pair hypotheses of `view_consensus`: it has
    every view, the neighbouring frames and the body's shape behind it, so it settles the
    frames where the views split evenly (the lab's man seen from behind by cam02 during a fast
    turn, read as facing it for 20 frames)."""
    o = options or ConsensusOptions()
    seen, uv, conf = _evidence(obs, o)
    X = np.asarray(markers, np.float64)[:, None]
    _, grp = _view_errors(obs, X, uv, conf, o.min_confidence)
    _, grp_sw = _view_errors(obs, X, uv[:, :, SWAP], conf[:, :, SWAP], o.min_confidence)
    grp, grp_sw = grp[:, 0], grp_sw[:, 0]
    limit = o.agree * _extent_px(obs, conf)
    with np.errstate(invalid="ignore"):
        clear = np.fmax(grp, grp_sw) > limit[..., None] / 2
        return seen[..., None] & clear & (grp_sw < o.swap_gain * grp)


def readings_against_body(
    obs: PersonObservations,
    other: np.ndarray,
    markers: np.ndarray,
    options: ConsensusOptions | None = None,
    gain: float = 1.0,
) -> np.ndarray:
    """(T, C) bool: the views whose `other` reading of the landmarks ((T, C, M, 3) u, v crop
    pixels and confidence; NaN where there is none) lies nearer the fitted body (`markers`
    (T, M, 3) world, on `obs.frames`) than the view's own, by more than `gain` (median error in
    full-image pixels, other < gain x own). The fitted body has every view behind it, so it can
    judge between two readings of one crop (gst.fuse.relook)."""
    o = options or ConsensusOptions()
    seen, uv, conf = _evidence(obs, o)
    other = np.asarray(other, np.float64)
    alt = replace(obs, uv=other[..., :2], confidence=np.nan_to_num(other[..., 2]))
    _, uv_alt, conf_alt = _evidence(alt, o)
    X = np.asarray(markers, np.float64)[:, None]
    own, _ = _view_errors(obs, X, uv, conf, o.min_confidence)
    theirs, _ = _view_errors(obs, X, uv_alt, conf_alt, o.min_confidence)
    with np.errstate(invalid="ignore"):
        return seen & (theirs[:, 0] < gain * np.where(np.isnan(own[:, 0]), np.inf, own[:, 0]))


def _extent_px(obs: PersonObservations, conf: np.ndarray) -> np.ndarray:
    """(T, C) the person's size in each view: the larger side of its confident landmarks' box,
    in full-image pixels (NaN where the view has fewer than 4 confident landmarks)."""
    ok = conf > 0
    with np.errstate(invalid="ignore"):
        lo = np.where(ok[..., None], obs.uv, np.inf).min(-2)
        hi = np.where(ok[..., None], obs.uv, -np.inf).max(-2)
    size = (hi - lo).max(-1) * obs.px_scale
    return np.where(ok.sum(-1) >= 4, size, np.nan)
