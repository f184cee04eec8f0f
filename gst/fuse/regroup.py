"""People as the rig sees them in 3D: crops regrouped by whole-skeleton agreement, tracked in time.

The extraction's person ids come from 2D association, frame by frame; where people overlap they
can be exchanged for a few frames, split in two, or a crop can show the other person. The view
consensus (gst.fuse.consensus) gives, for every extraction person-frame, a 3D skeleton
hypothesis backed by at least `min_agree` cameras. Here:

1. per frame, hypotheses closer than `merge_m` (mean distance of the shoulders and hips) are one
   person (two extraction ids on the same body): the one backed by more views stands;
2. hypotheses are linked into tracks over time by the Hungarian method on that distance to each
   track's last position, gated at `jump_mps` (m/s) times the time elapsed, and for at most
   `max_gap_s` seconds, with a bonus `same_id_m` for the
   extraction id the track came from; a hypothesis left over starts a new track;
3. per frame, every crop of every extraction person goes to the track whose skeleton it matches
   best (median landmark error below `agree` x the person's size in that view; one crop per
   camera and track), so a crop that showed the other person joins that person;
4. extraction person-frames without a hypothesis (fewer than `min_agree` agreeing views) keep
   their crops with the track that last took a hypothesis of that extraction id, and that track
   continues when the id's next hypothesis comes, however long the wait.

The result is one `PersonObservations` per track, with the view consensus applied (exchanged
limb groups put right, unmatched views dropped).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from gst.fuse.consensus import ConsensusOptions, view_consensus
from gst.fuse.observations import PersonObservations

__all__ = ["RegroupOptions", "RegroupReport", "regroup_people"]

_TORSO = [11, 12, 23, 24]


@dataclass(frozen=True)
class RegroupOptions:
    consensus: ConsensusOptions = field(default_factory=ConsensusOptions)
    merge_m: float = 0.2
    # The gates are in time, not frames (they were 0.3 m per frame and 15 frames: 18 m/s and
    # 0.25 s at the lab's 60 fps, 7.5 m/s at 25 fps); the same as before at 30 fps.
    jump_mps: float = 9.0  # how fast a torso may move between its hypotheses
    same_id_m: float = 0.1
    max_gap_s: float = 0.5  # a track not seen this long takes no hypothesis


@dataclass
class RegroupReport:
    tracks: int
    moved_crops: int  # crops given to another person than their extraction id
    merged: int  # person-frames where two extraction ids were one body
    track_of: dict[int, list[int]]  # track id -> extraction ids it took crops from


def _torso_distance(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a[_TORSO] - b[_TORSO], axis=-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        v = np.nanmean(d)
    return float(v) if np.isfinite(v) else np.inf


def _median_errors(obs: PersonObservations, t: int, X: np.ndarray, min_conf: float) -> np.ndarray:
    """(C,) median landmark error (full px) of each view of obs frame t against points X."""
    P = obs.K[t] @ obs.Rt[t]  # (C, 3, 4)
    q = np.einsum("cij,mj->cmi", P, np.c_[X, np.ones(len(X))])
    with np.errstate(invalid="ignore", divide="ignore"):
        p = q[..., :2] / q[..., 2:]
    ok = (obs.confidence[t] >= min_conf) & (q[..., 2] > 0) & np.isfinite(X).all(-1)
    e = np.where(ok, np.linalg.norm(p - obs.uv[t], axis=-1) * obs.px_scale[t][:, None], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(e, -1)


def _extent(obs: PersonObservations, t: int, min_conf: float) -> np.ndarray:
    # a landmark without pixels is no reading, whatever its confidence (its NaN made the
    # view's size NaN: the view then matched no skeleton and was dropped)
    ok = (obs.confidence[t] >= min_conf) & np.isfinite(obs.uv[t]).all(-1)
    lo = np.where(ok[..., None], obs.uv[t], np.inf).min(-2)
    hi = np.where(ok[..., None], obs.uv[t], -np.inf).max(-2)
    size = (hi - lo).max(-1) * obs.px_scale[t]
    return np.where(ok.sum(-1) >= 4, size, np.nan)


def regroup_people(
    people: list[PersonObservations], options: RegroupOptions | None = None, fps: float = 30.0
) -> tuple[list[PersonObservations], RegroupReport]:
    """The module's steps on `people` (one per extraction id) of a capture at `fps` (the frame
    numbers are video frames)."""
    o = options or RegroupOptions()
    if not (np.isfinite(fps) and fps > 0):  # the gates are per second: 0 divided, NaN broke round
        raise ValueError(f"regroup_people needs a frame rate fps > 0, got {fps}")
    jump_per_frame, max_gap = o.jump_mps / fps, round(o.max_gap_s * fps)
    if not people:
        return [], RegroupReport(0, 0, 0, {})
    C, M = people[0].uv.shape[1:3]
    fixed, hyp = [], {}  # hyp[frame] -> list of (extraction index, points, agreeing)
    for k, p in enumerate(people):
        q, rep = view_consensus(p, o.consensus)
        # dropped views may show another person: keep their landmarks for step 3, as read (a
        # limb exchange decided against this person's skeleton is undone with them: it left
        # the pixels exchanged and the confidences not)
        q.uv[rep.dropped] = p.uv[rep.dropped]
        q.confidence[rep.dropped] = p.confidence[rep.dropped]
        fixed.append(q)
        for t, f in enumerate(p.frames):
            if (
                rep.agreeing[t] >= o.consensus.min_agree
                and np.isfinite(rep.points[t][_TORSO]).any()
            ):
                hyp.setdefault(int(f), []).append((k, rep.points[t], int(rep.agreeing[t])))
    index = [{int(f): t for t, f in enumerate(p.frames)} for p in people]
    frames = sorted({int(f) for p in people for f in p.frames})
    ids = [p.person_id for p in people]
    tracks: dict[int, dict] = {}  # id -> {"X", "frame", "source"}
    holder: dict[int, int] = {}  # extraction index -> track id that last took its hypothesis
    assigned: dict[int, dict[int, tuple[int, int]]] = {}  # track -> frame -> {camera: (k, t)}
    moved = merged = 0
    next_id = max(ids) + 1
    for f in frames:
        cands = sorted(hyp.get(f, []), key=lambda h: -h[2])
        keep = []
        for h in cands:  # merge duplicates: the better-backed hypothesis stands
            if all(_torso_distance(h[1], g[1]) > o.merge_m for g in keep):
                keep.append(h)
            else:
                merged += 1
        live = [tid for tid, tr in tracks.items() if f - tr["frame"] <= max_gap]
        cost = np.full((len(keep), len(live)), np.inf)
        for i, (k, X, _) in enumerate(keep):
            for j, tid in enumerate(live):
                tr = tracks[tid]
                d = _torso_distance(X, tr["X"])
                if d <= jump_per_frame * (f - tr["frame"]):
                    cost[i, j] = d - (o.same_id_m if tr["source"] == k else 0.0)
        taken = {}
        if keep and live:
            finite = np.where(np.isfinite(cost), cost, 1e6)
            r, c = linear_sum_assignment(finite)
            taken = {i: live[j] for i, j in zip(r, c, strict=True) if np.isfinite(cost[i, j])}
        used = set(taken.values())
        for i, (k, X, _) in enumerate(keep):
            tid = taken.get(i)
            if tid is None and holder.get(k) is not None and holder[k] not in used:
                tid = holder[k]  # the track that kept this id's crops while it had no skeleton
            if tid is None:
                tid = ids[k] if ids[k] not in tracks and ids[k] not in used else next_id
                next_id = max(next_id, tid + 1)
            used.add(tid)
            tracks[tid] = {"X": X, "frame": f, "source": k}
            holder[k] = tid
        # every crop of this frame to the track whose skeleton it matches best
        now = [tid for tid, tr in tracks.items() if tr["frame"] == f]
        best: dict[tuple[int, int], tuple[float, int, int]] = {}  # (track, camera) -> (err, k, t)
        for k, p in enumerate(fixed):
            t = index[k].get(f)
            if t is None:
                continue
            lim = o.consensus.agree * _extent(p, t, o.consensus.min_confidence)
            errs = {tid: _median_errors(p, t, tracks[tid]["X"], o.consensus.min_confidence)
                    for tid in now}  # fmt: skip
            for c in np.flatnonzero(p.rows[t] >= 0):
                scores = [(errs[tid][c], tid) for tid in now if errs[tid][c] < lim[c]]
                if scores:
                    e, tid = min(scores)
                elif k in holder and holder[k] not in now:
                    tid, e = holder[k], np.inf  # no hypothesis here: stays with its holder
                elif not now or k not in holder:
                    tid, e = ids[k], np.inf
                else:
                    continue  # matches no skeleton of this frame: dropped
                if (tid, c) not in best or e < best[(tid, c)][0]:
                    best[(tid, c)] = (e, k, t)
        for (tid, c), (_, k, t) in best.items():
            assigned.setdefault(tid, {}).setdefault(f, {})[c] = (k, t)
            moved += int(tid != holder.get(k, ids[k]) and tid != ids[k])
    out = []
    track_of = {}
    for tid in sorted(assigned):
        fr = sorted(assigned[tid])
        T = len(fr)
        obs = PersonObservations(
            tid, np.array(fr, np.int64),
            np.full((T, C, M, 2), np.nan), np.zeros((T, C, M)),
            np.broadcast_to(np.eye(3), (T, C, 3, 3)).copy(),
            np.broadcast_to(np.eye(3, 4), (T, C, 3, 4)).copy(),
            np.ones((T, C)), np.full((T, C), -1, np.int64),
        )  # fmt: skip
        sources = set()
        for i, f in enumerate(fr):
            for c, (k, t) in assigned[tid][f].items():
                src = fixed[k]
                obs.uv[i, c], obs.confidence[i, c] = src.uv[t, c], src.confidence[t, c]
                obs.K[i, c], obs.Rt[i, c] = src.K[t, c], src.Rt[t, c]
                obs.px_scale[i, c], obs.rows[i, c] = src.px_scale[t, c], src.rows[t, c]
                sources.add(ids[k])
        # views the consensus dropped (no usable landmark) are no observation at all
        empty = (obs.rows >= 0) & ~(obs.confidence > 0).any(-1)
        obs.rows[empty] = -1
        obs.uv[empty] = np.nan
        seen = (obs.rows >= 0).any(1)
        if not seen.any():
            continue
        obs = obs.select(seen)
        track_of[tid] = sorted(sources)
        out.append(obs)
    return out, RegroupReport(len(out), moved, merged, track_of)
