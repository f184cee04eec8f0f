"""Person ids across frames: Hungarian assignment on box overlap, 3D position, appearance and
skeleton.

Each track keeps a constant-velocity model of its box (px/s) and of its 3D position (m/s), an
exponential average of its colour histogram, and the landmarks of its last detection. For a new
frame the cost of giving detection j to track i is the weighted mean of terms in [0, 1]:

    1 - IoU(predicted box_i, box_j)
    min(|predicted position_i - position_j| / gate_i, 1),  gate_i = noise + max_speed * dt_i
    Hellinger(appearance_i, appearance_j)
    min(median |limb landmark_j - limb landmark_i moved with the box| / (scale * size_i), 1)

The skeleton term counts only for pairs where both have landmarks (the learned person model's),
over the limb joints both are sure of (at least 4): where two people overlap, their boxes and
colours are alike but their limbs are not (docs/track_evaluation.md, "Crowds").

A pair is allowed only if its cost is at most `max_cost`, the boxes overlap (IoU >= min_iou) or
the 3D positions are within the gate, and the positions are within `hard_gate` gates (a
generous bound, since monocular depth is noisy). scipy's linear_sum_assignment picks the cheapest
allowed matching, confirmed tracks first and tentative ones among the detections left (a
duplicate detection's tentative track cannot take a person over). Unmatched tracks coast on
their velocity for up to `max_misses` processed frames (short occlusions), then end; unmatched
detections start tentative tracks. A tentative track gets its id only once it has been matched
in `min_hits` consecutive processed frames (until then its detections get id -1, and one miss
ends it), so flickering fragments and false detections do not use up ids. Their detections are
not lost: when a track is confirmed, `step` hands back the keys of the observations it made while
tentative (`Assignment.backfill`), so the person's rows start where they appeared.

One person, one id (gst.track.parts): an observation left unmatched by the confirmed tracks that
lies mostly inside the box of an observation a confirmed track took in the same frame, and is a
part of that person (its skeleton lies on theirs; without landmarks, its appearance and 3D
position do not both disagree), starts no track and extends no tentative one.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from gst.detect.boxes import box_iou  # noqa: F401  (re-exported: gst.track.box_iou)
from gst.detect.persons import LIMB_JOINTS, body_size
from gst.track.appearance import hellinger
from gst.track.parts import PartConfig, is_part

_INFEASIBLE = 1e6


@dataclass(frozen=True)
class TrackerConfig:
    w_iou: float = 1.0
    w_position: float = 1.0
    w_appearance: float = 1.0
    # pairs where both have landmarks: how far the detection's limb joints lie from the track's
    # last ones (moved with its predicted box), per `skeleton_scale` of the track's body size
    # (gst.detect.persons.body_size); on the synthetic crowd scenes 95 -> 75 id switches
    w_skeleton: float = 1.0
    skeleton_scale: float = 0.3
    max_cost: float = 0.75
    min_iou: float = 0.05  # below this overlap a pair must be close in 3D to match
    position_noise_m: float = 0.5  # 3D gate at zero elapsed time (monocular depth is noisy)
    max_speed_mps: float = 10.0  # the 3D gate grows by this much per second unseen
    hard_gate: float = 3.0  # pairs further apart than this many gates never match
    max_misses: int = 15  # processed frames a track survives undetected
    velocity_weight: float = 0.5  # weight of the newest velocity in its running average
    appearance_weight: float = 0.2  # weight of the newest histogram in its running average
    min_score_new: float = 0.0  # detections scoring below this never start a track
    min_hits: int = 1  # consecutive matches before a new track gets an id (1: at once)
    parts: PartConfig | None = field(default_factory=PartConfig)  # None: no part test

    def __post_init__(self):
        if (
            min(self.w_iou, self.w_position, self.w_appearance, self.w_skeleton) < 0
            or self.w_iou + self.w_position + self.w_appearance <= 0
        ):
            raise ValueError(
                "tracker weights must be >= 0 and those of box, position and appearance not all "
                f"0, got {self.w_iou}, {self.w_position}, {self.w_appearance}, {self.w_skeleton}"
            )
        if self.skeleton_scale <= 0:
            raise ValueError(f"skeleton_scale must be > 0, got {self.skeleton_scale}")
        if self.max_misses < 0:
            raise ValueError(f"max_misses must be >= 0, got {self.max_misses}")
        if self.min_hits < 1:
            raise ValueError(f"min_hits must be >= 1, got {self.min_hits}")
        for name in ("velocity_weight", "appearance_weight"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        # a gate of 0 at zero elapsed time divided by zero (two updates at one time stamp)
        for name in ("position_noise_m", "hard_gate", "max_cost"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.max_speed_mps < 0:
            raise ValueError(f"max_speed_mps must be >= 0, got {self.max_speed_mps}")


@dataclass
class Observation:
    """What the tracker sees of one detection."""

    box: np.ndarray  # (4,) x0, y0, x1, y1 px
    position: np.ndarray  # (3,) metres (pelvis; world frame when calibrated, else camera)
    appearance: np.ndarray  # (D,) histogram summing to 1
    score: float = 1.0
    key: tuple | None = None  # the caller's name for it (handed back when a track is confirmed)
    landmarks: np.ndarray | None = None  # (33, 3) u, v, confidence in frame pixels, if known


@dataclass
class Assignment:
    """What `Tracker.step` decided for one frame."""

    ids: list[int]  # per observation: its track's id, or -1 (tentative track, part, dropped)
    backfill: list[tuple[tuple, int]]  # (key, id) of earlier observations of tracks confirmed now
    parts: list[int]  # indices of observations found to be parts of a confirmed person


@dataclass
class Track:
    id: int
    box: np.ndarray
    position: np.ndarray
    appearance: np.ndarray
    last_time: float
    box_velocity: np.ndarray = field(default_factory=lambda: np.zeros(4))
    position_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hits: int = 1
    misses: int = 0
    confirmed: bool = True  # False while a new track has fewer than min_hits matches (id -1)
    pending: list = field(default_factory=list)  # keys of its observations while tentative
    landmarks: np.ndarray | None = None  # (33, 3) of its last observation, where it had them

    def predicted_box(self, time_s: float) -> np.ndarray:
        return self.box + self.box_velocity * (time_s - self.last_time)

    def predicted_position(self, time_s: float) -> np.ndarray:
        return self.position + self.position_velocity * (time_s - self.last_time)

    def to_dict(self) -> dict:
        return {
            k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()
        }

    @classmethod
    def from_dict(cls, d: dict) -> Track:
        arrays = ("box", "position", "appearance", "box_velocity", "position_velocity")
        d = {k: (np.asarray(v, dtype=np.float64) if k in arrays else v) for k, v in d.items()}
        if d.get("landmarks") is not None:
            d["landmarks"] = np.asarray(d["landmarks"], dtype=np.float64)
        d["pending"] = [tuple(k) for k in d.get("pending", [])]
        return cls(**d)


def _publish(track: Track) -> int | None:
    return track.id if track.confirmed else None


class Tracker:
    """Online multi-person tracker; `update` once per processed frame, in time order."""

    def __init__(self, config: TrackerConfig | None = None):
        self.config = config or TrackerConfig()
        self.tracks: list[Track] = []
        self.next_id = 0

    def cost_matrix(
        self, time_s: float, observations: list[Observation]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(cost (T, N), allowed (T, N)) between live tracks and observations."""
        c = self.config
        T, N = len(self.tracks), len(observations)
        if T == 0 or N == 0:
            return np.zeros((T, N)), np.zeros((T, N), bool)
        pred_boxes = np.stack([t.predicted_box(time_s) for t in self.tracks])
        pred_pos = np.stack([t.predicted_position(time_s) for t in self.tracks])
        gates = np.array(
            [
                c.position_noise_m + c.max_speed_mps * max(time_s - t.last_time, 0.0)
                for t in self.tracks
            ]
        )
        boxes = np.stack([o.box for o in observations])
        pos = np.stack([o.position for o in observations])
        iou = box_iou(pred_boxes, boxes)
        dist = np.linalg.norm(pred_pos[:, None] - pos[None], axis=-1)
        app = hellinger(
            np.stack([t.appearance for t in self.tracks])[:, None],
            np.stack([o.appearance for o in observations])[None],
        )
        skeleton, has = self._skeleton_distances(time_s, observations)
        w_skeleton = c.w_skeleton * has  # (T, N): the term counts where both have landmarks
        cost = (
            c.w_iou * (1 - iou)
            + c.w_position * np.minimum(dist / gates[:, None], 1.0)
            + c.w_appearance * app
            + w_skeleton * skeleton
        ) / (c.w_iou + c.w_position + c.w_appearance + w_skeleton)
        allowed = (
            (cost <= c.max_cost)
            & ((iou >= c.min_iou) | (dist <= gates[:, None]))
            & (dist <= c.hard_gate * gates[:, None])
        )
        return cost, allowed

    def _skeleton_distances(
        self, time_s: float, observations: list[Observation]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(T, N) skeleton term in [0, 1], and (T, N) 1.0 where it is defined: both have
        landmarks, and at least 4 limb joints are sure (>= 0.5) on both sides."""
        c = self.config
        T, N = len(self.tracks), len(observations)
        term, has = np.zeros((T, N)), np.zeros((T, N))
        mine = [i for i, t in enumerate(self.tracks) if t.landmarks is not None]
        theirs = [j for j, o in enumerate(observations) if o.landmarks is not None]
        if c.w_skeleton <= 0 or not mine or not theirs:
            return term, has
        tracks = [self.tracks[i] for i in mine]
        a = np.stack([t.landmarks[LIMB_JOINTS] for t in tracks])  # (T', 12, 3)
        b = np.stack([np.asarray(observations[j].landmarks)[LIMB_JOINTS] for j in theirs])
        # each track's skeleton moved as its box is predicted to move
        shift = np.stack([t.predicted_box(time_s) - t.box for t in tracks])
        moved = a[..., :2] + ((shift[:, :2] + shift[:, 2:]) / 2)[:, None]
        d = np.linalg.norm(moved[:, None] - b[None, :, :, :2], axis=-1)  # (T', N', 12)
        sure = (a[:, None, :, 2] >= 0.5) & (b[None, :, :, 2] >= 0.5)
        enough = sure.sum(-1) >= 4
        median = np.ma.median(np.ma.array(d, mask=~sure), axis=-1).filled(0.0)
        median = np.where(enough, median, 0.0)
        scale = c.skeleton_scale * np.maximum([body_size(t.landmarks) for t in tracks], 1.0)
        value = np.minimum(median / scale[:, None], 1.0)
        term[np.ix_(mine, theirs)] = value
        has[np.ix_(mine, theirs)] = enough
        return term, has

    def update(self, time_s: float, observations: list[Observation]) -> list[int]:
        """Assign an id to each observation (same order) and advance every track."""
        return self.step(time_s, observations).ids

    def pending_keys(self) -> set:
        """Keys of the observations of live tentative tracks (they may still get an id)."""
        return {k for t in self.tracks if not t.confirmed for k in t.pending}

    def _parts(
        self, time_s: float, observations: list[Observation], taken: dict[int, int], free: list[int]
    ) -> list[int]:
        """Observations in `free` that are parts of a person a confirmed track took this frame
        (`taken`: observation -> track row)."""
        c = self.config
        if c.parts is None or not taken:
            return []
        gate = c.position_noise_m
        out = []
        for j in free:
            o = observations[j]
            for i, r in taken.items():
                t, outer = self.tracks[r], observations[i]
                if is_part(
                    o.box,
                    outer.box,
                    o.landmarks,
                    outer.landmarks,
                    float(hellinger(t.appearance, o.appearance)),
                    float(np.linalg.norm(t.predicted_position(time_s) - o.position)) > gate,
                    c.parts,
                ):
                    out.append(j)
                    break
        return out

    def step(self, time_s: float, observations: list[Observation]) -> Assignment:
        """Match one frame's observations to the tracks and advance every track."""
        c = self.config
        cost, allowed = self.cost_matrix(time_s, observations)
        ids: list[int | None] = [None] * len(observations)
        matched_tracks: set[int] = set()
        matched_obs: set[int] = set()
        backfill: list[tuple[tuple, int]] = []
        parts: list[int] = []
        taken: dict[int, int] = {}  # observation -> confirmed track row that took it
        # Confirmed tracks choose first, tentative ones share what is left: a duplicate
        # detection's tentative track must not take a person over from their own track.
        for confirmed in (True, False):
            rows_in = [r for r, t in enumerate(self.tracks) if t.confirmed == confirmed]
            cols_in = [j for j in range(len(observations)) if j not in matched_obs]
            if not confirmed:
                parts = self._parts(time_s, observations, taken, cols_in)
                cols_in = [j for j in cols_in if j not in parts]
            if not rows_in or not cols_in:
                continue
            sub_cost = cost[np.ix_(rows_in, cols_in)]
            sub_ok = allowed[np.ix_(rows_in, cols_in)]
            rows, cols = linear_sum_assignment(np.where(sub_ok, sub_cost, _INFEASIBLE))
            for a, b in zip(rows, cols, strict=True):
                if not sub_ok[a, b]:
                    continue
                r, j = rows_in[a], cols_in[b]
                t = self.tracks[r]
                self._absorb(t, observations[j], time_s)
                if not t.confirmed:
                    t.pending.append(observations[j].key)
                    if t.hits >= c.min_hits:
                        t.confirmed, t.id = True, self.next_id
                        self.next_id += 1
                        backfill += [(k, t.id) for k in t.pending[:-1] if k is not None]
                        t.pending = []
                ids[j] = _publish(t)
                matched_tracks.add(r)
                matched_obs.add(j)
                if confirmed:
                    taken[j] = r
        survivors = []
        for r, t in enumerate(self.tracks):
            if r not in matched_tracks:
                t.misses += 1
            if t.misses <= (c.max_misses if t.confirmed else 0):
                survivors.append(t)
        self.tracks = survivors
        unmatched = [
            j
            for j, obs in enumerate(observations)
            if j not in matched_obs and j not in parts and obs.score >= c.min_score_new
        ]
        for j in unmatched:
            obs = observations[j]
            confirmed = c.min_hits <= 1
            t = Track(
                self.next_id if confirmed else -1,
                obs.box.copy(),
                obs.position.copy(),
                obs.appearance.copy(),
                time_s,
                confirmed=confirmed,
                pending=[] if confirmed else [obs.key],
                landmarks=None if obs.landmarks is None else np.asarray(obs.landmarks, np.float64),
            )
            if confirmed:
                self.next_id += 1
            self.tracks.append(t)
            ids[j] = _publish(t)
        return Assignment([-1 if i is None else i for i in ids], backfill, parts)

    def _absorb(self, t: Track, obs: Observation, time_s: float) -> None:
        c = self.config
        dt = time_s - t.last_time
        if dt > 0:
            w = 1.0 if t.hits == 1 else c.velocity_weight
            t.box_velocity = w * (obs.box - t.box) / dt + (1 - w) * t.box_velocity
            t.position_velocity = (
                w * (obs.position - t.position) / dt + (1 - w) * t.position_velocity
            )
        t.box, t.position, t.last_time = obs.box.copy(), obs.position.copy(), time_s
        if obs.landmarks is not None:
            t.landmarks = np.asarray(obs.landmarks, np.float64).copy()
        a = c.appearance_weight
        t.appearance = a * obs.appearance + (1 - a) * t.appearance
        t.hits += 1
        t.misses = 0

    def state_dict(self) -> dict:
        """JSON-serialisable state (floats round-trip exactly through json)."""
        return {"next_id": self.next_id, "tracks": [t.to_dict() for t in self.tracks]}

    def load_state_dict(self, state: dict) -> None:
        self.next_id = int(state["next_id"])
        self.tracks = [Track.from_dict(d) for d in state["tracks"]]
