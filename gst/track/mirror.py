"""Left/right labels kept continuous over time: BlazePose's whole-body flips undone in video.

The landmark model sometimes labels a whole person's left side as right (mostly in side-on
views: docs/landmark_prior.md measures 6 % of rendered crops). The network, fed those landmarks,
turns the body to face the other way, and every left joint angle in the Parquet becomes the
right one. In a video the flip shows itself: from one frame to the next the left landmarks jump
to where the right ones were. A single image cannot tell (docs/training.md, "Mirrored
landmarks"), a sequence can.

Per person (detections linked from frame to frame by their mid-hips), two states per frame: the
labels as given, or exchanged. The chosen sequence minimises
- `prior_per_s` x seconds spent exchanged (the landmark model is right most of the time), plus
- per pair of consecutive frames, the mean distance of the six limb pairs (shoulders, elbows,
  wrists, hips, knees, ankles; sure on both sides) between the two frames' labels as the states
  have them, after removing the body's own move, in torso lengths, divided by `sigma`.

Inside the video, a path still exchanged at the look-ahead's end also pays the jump back to the
labels as detected (`end_jump`): a jump with no return within the look-ahead is a real turn.
A fixed-lag smoother (Viterbi over the next `lag_s` seconds, the earlier frames' states fixed)
decides each frame before it leaves, so tracking stays a stream with `lag_s` of look-ahead
(`LabelSmoother`; the tracking loop holds back each frame's small per-person records for that
long, after the crops are cut, never the frame itself).
Measured in docs/track_evaluation.md, "Left and right".
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

# (left, right) BlazePose landmarks compared between frames
LIMB_PAIRS = ((11, 12), (13, 14), (15, 16), (23, 24), (25, 26), (27, 28))
_LEFT = np.array([p[0] for p in LIMB_PAIRS])
_RIGHT = np.array([p[1] for p in LIMB_PAIRS])
_HIPS, _SHOULDERS = [23, 24], [11, 12]


@dataclass(frozen=True)
class MirrorConfig:
    lag_s: float = 1.0  # look-ahead before a frame's labels are decided (0.5 before 12-01)
    # a path still exchanged at the look-ahead's end pays the jump back to the labels as
    # detected (`LabelSmoother._decide`; False: before 12-01, when a real quick turn stayed
    # exchanged to the end of the video)
    end_jump: bool = True
    prior_per_s: float = 15.0  # cost of one second with the labels exchanged
    sigma: float = 0.1  # torso lengths of inter-frame distance per unit of cost
    min_confidence: float = 0.5  # landmarks compared (both frames)
    min_pairs: int = 3  # fewer sure pairs: the step carries no evidence
    link_torso: float = 1.0  # mid-hips farther than this (torso lengths) start a new person
    max_gap: int = 3  # processed frames a person may be missing and keep their history

    def __post_init__(self):
        if self.lag_s < 0 or self.prior_per_s <= 0 or self.sigma <= 0:
            raise ValueError(
                f"MirrorConfig: lag_s >= 0, prior_per_s > 0 and sigma > 0 expected, got "
                f"{self.lag_s}, {self.prior_per_s}, {self.sigma}"
            )


def _torso(lm: np.ndarray) -> float:
    return float(np.linalg.norm(lm[_SHOULDERS, :2].mean(0) - lm[_HIPS, :2].mean(0)))


def _scale(a: np.ndarray, b: np.ndarray) -> float:
    """Torso length comparing frame a with frame b: a's, else b's where a has none (shoulders
    without a position give NaN: one such frame cut the person's chain and hid the jump of a
    flip starting right after it), NaN where neither has one."""
    size = _torso(a)
    return size if size > 1e-6 else _torso(b)


def step_costs(a: np.ndarray, b: np.ndarray, config: MirrorConfig) -> tuple[float, float]:
    """(kept, exchanged): mean distance of the sure limb pairs from frame a's (33, 3) landmarks
    to frame b's, b's labels as given or exchanged, b moved by the sure pairs' mean shift (which
    the labels do not change), in a's torso lengths (b's where a has none). (0, 0) where fewer
    than `min_pairs` pairs are sure on both sides or neither torso has a length: no evidence
    either way."""
    conf = np.minimum.reduce([a[_LEFT, 2], a[_RIGHT, 2], b[_LEFT, 2], b[_RIGHT, 2]])
    placed = np.isfinite(np.concatenate([a[_LEFT], a[_RIGHT], b[_LEFT], b[_RIGHT]], 1)).all(1)
    sure = placed & np.isfinite(conf) & (conf >= config.min_confidence)
    size = _scale(a, b)
    if int(sure.sum()) < config.min_pairs or not size > 1e-6:
        return 0.0, 0.0
    al, ar = a[_LEFT, :2][sure], a[_RIGHT, :2][sure]
    shift = (al + ar).mean(0) / 2 - (b[_LEFT, :2][sure] + b[_RIGHT, :2][sure]).mean(0) / 2
    bl, br = b[_LEFT, :2][sure] + shift, b[_RIGHT, :2][sure] + shift
    kept = np.linalg.norm(bl - al, axis=1) + np.linalg.norm(br - ar, axis=1)
    exchanged = np.linalg.norm(bl - ar, axis=1) + np.linalg.norm(br - al, axis=1)
    n = 2 * len(al)
    return float(kept.sum() / n / size), float(exchanged.sum() / n / size)


def node_state(
    start: int | None,
    steps: list[tuple[float, float]],
    prior: float,
    sigma: float,
    back: float = 0.0,
) -> int:
    """Viterbi over two states (0 labels kept, 1 exchanged) for nodes 0..len(steps) - 1 of a
    chain; `steps[k]` = (kept, exchanged) costs from node k - 1 to node k, where node -1 is the
    fixed, already decided `start` state (None: no such node, node 0 is free and steps[0] is not
    read). Each exchanged node costs `prior`; a path still exchanged at the last node pays `back`
    (the step back to the labels as detected that it must take later). Returns node 0's state."""
    if start is None:
        cost = [0.0, prior]
    else:
        kept, exchanged = steps[0][0] / sigma, steps[0][1] / sigma
        cost = [kept, exchanged + prior] if start == 0 else [exchanged, kept + prior]
    # only node 0's state is wanted: carry, per current state, the node-0 state of its best path
    origin = [0, 1]
    for kept, exchanged in steps[1:]:
        same, cross = kept / sigma, exchanged / sigma
        to0 = (cost[0] + same, cost[1] + cross)  # from a kept / exchanged node to a kept one
        to1 = (cost[0] + cross + prior, cost[1] + same + prior)
        k0, k1 = int(to0[1] < to0[0]), int(to1[1] < to1[0])
        cost, origin = [to0[k0], to1[k1]], [origin[k0], origin[k1]]
    return origin[int(cost[1] + back < cost[0])]


@dataclass
class _Chain:
    """One person's frames: the undecided ones' steps (costs from the frame before; None at the
    chain's start), oldest first, and what the next frame is compared with."""

    last: np.ndarray  # newest raw landmarks (33, 3)
    last_frame: int  # processed-frame count at which they were seen
    steps: deque = field(default_factory=deque)
    decided: int | None = None  # state of the newest decided frame (None: none yet)


def _link(chains: dict[int, _Chain], lms: list[np.ndarray | None], now: int, c: MirrorConfig):
    """Chain key per detection (None: no landmarks): nearest live chain by mid-hips, within
    `link_torso` torso lengths, one-to-one; None for those that start a chain."""
    live = [k for k, ch in chains.items() if now - ch.last_frame <= c.max_gap + 1]
    cand = [i for i, lm in enumerate(lms) if lm is not None and np.isfinite(lm[_HIPS]).all()]
    out: list[int | None] = [None] * len(lms)
    if live and cand:
        cost = np.full((len(live), len(cand)), np.inf)
        for r, k in enumerate(live):
            prev = chains[k].last
            for col, i in enumerate(cand):
                size = max(_scale(prev, lms[i]), 1e-6)  # NaN (neither has a torso): no link
                d = np.linalg.norm(lms[i][_HIPS, :2].mean(0) - prev[_HIPS, :2].mean(0)) / size
                if d <= c.link_torso:
                    cost[r, col] = d
        # pairs beyond the gate cost more than any allowed one and are dropped after
        rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, c.link_torso + 1))
        for r, col in zip(rows, cols, strict=True):
            if np.isfinite(cost[r, col]):
                out[cand[col]] = live[r]
    return out


class LabelSmoother:
    """The fixed-lag smoother over a stream of frames (module docstring).

    `push(payload, landmarks)` takes one processed frame: anything the caller wants back
    (`payload`) and each person's (33, 3) landmarks, u, v, confidence (None where a detection has
    none). It returns the frames whose labels are now decided, oldest first, each as (payload,
    flags): per person, True where their labels are to be exchanged. The caller exchanges them
    (`BLAZEPOSE_MIRROR`). `flush()` decides and returns what is left (end of the video, or before
    an error is raised). Only landmarks are held back, never images.

    `with_state`: each decided frame comes as (payload, flags, state) instead, `state` being what
    a smoother restarted after that frame needs (JSON-ready; `load_state_dict`) to decide the
    frames after it exactly as this one does: a resumed tracking run continues from it."""

    def __init__(self, config: MirrorConfig, frame_interval_s: float, with_state: bool = False):
        if not frame_interval_s > 0:
            raise ValueError(f"frame interval must be > 0 s, got {frame_interval_s}")
        self.config = config
        self.lag = max(0, math.ceil(config.lag_s / frame_interval_s - 1e-9))
        self.prior = config.prior_per_s * frame_interval_s
        self.with_state = with_state
        self._chains: dict[int, _Chain] = {}
        self._next_key = 0
        self._count = -1
        # (payload, chain key per person, their landmarks, the frame's count, the next key)
        self._buffer: deque = deque()
        # per chain, as of the newest decided frame it was in: (state, landmarks, count)
        self._decided: dict[int, tuple[int, np.ndarray, int]] = {}

    def load_state_dict(self, state: dict) -> None:
        """Continue after the frame whose decision gave `state` (an empty smoother only)."""
        if self._buffer or self._chains:
            raise RuntimeError("LabelSmoother.load_state_dict: the smoother has been used")
        self._count, self._next_key = int(state["count"]), int(state["next_key"])
        for key, decided, lm, count in state["chains"]:
            lm = np.asarray(lm, np.float64).reshape(-1, 3)
            self._chains[int(key)] = _Chain(lm, int(count), deque(), int(decided))
            self._decided[int(key)] = (int(decided), lm, int(count))

    def push(self, payload, landmarks) -> list[tuple[object, list[bool]]]:
        c = self.config
        self._count += 1
        lms = [None if lm is None else np.asarray(lm, np.float64) for lm in landmarks]
        links = _link(self._chains, lms, self._count, c)
        for i, (lm, k) in enumerate(zip(lms, links, strict=True)):
            if k is not None:
                ch = self._chains[k]
                ch.steps.append(step_costs(ch.last, lm, c))
                ch.last, ch.last_frame = lm, self._count
            elif lm is not None and np.isfinite(lm[_HIPS]).all():
                self._chains[self._next_key] = _Chain(lm, self._count, deque([None]))
                links[i], self._next_key = self._next_key, self._next_key + 1
        # people gone for good whose frames have all been decided are forgotten
        for k in [k for k, ch in self._chains.items() if not ch.steps]:
            if self._count - self._chains[k].last_frame > c.max_gap + 1:
                del self._chains[k]
                self._decided.pop(k, None)
        self._buffer.append((payload, links, lms, self._count, self._next_key))
        out = []
        while len(self._buffer) > self.lag:
            out.append(self._decide())
        return out

    def flush(self) -> list[tuple]:
        return [self._decide(at_end=True) for _ in range(len(self._buffer))]

    def _decide(self, at_end: bool = False) -> tuple:
        payload, links, lms, count, next_key = self._buffer.popleft()
        flags = []
        for k, lm in zip(links, lms, strict=True):
            if k is None:
                flags.append(False)
                continue
            ch = self._chains[k]
            step = ch.steps.popleft()
            # this frame's state given the decided one before it (none at a chain's start)
            start = None if step is None else ch.decided
            steps = [step or (0.0, 0.0), *(s or (0.0, 0.0) for s in ch.steps)]
            # Inside the video, labels still exchanged at the window's end must jump back later
            # (the landmark model is right most of the time): a path that does pays that jump,
            # the newest frame's left/right spread. Without it a real quick turn between two
            # processed frames (stride > 1, or missed frames) looked like a flip and, with arms
            # or legs spread, stayed exchanged to the end of the video; a flip longer than the
            # look-ahead now stays as detected, like a turn (the two cannot be told apart).
            end_jump = self.config.end_jump and not at_end
            back = step_costs(ch.last, ch.last, self.config)[1] if end_jump else 0.0
            ch.decided = node_state(
                start, steps, self.prior, self.config.sigma, back / self.config.sigma
            )
            flags.append(bool(ch.decided))
            self._decided[k] = (ch.decided, lm, count)
        if not self.with_state:
            return payload, flags
        # chains forgotten (gone for good) or started after this frame are left out
        chains = [
            [k, d, lm.tolist(), c]
            for k, (d, lm, c) in sorted(self._decided.items())
            if k in self._chains and k < next_key
        ]
        return payload, flags, {"count": count, "next_key": next_key, "chains": chains}
