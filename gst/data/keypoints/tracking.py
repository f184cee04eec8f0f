"""Global person ids over time from each frame's 3D people.

`PersonIdTracker.update(frame, match)` gives every group of a `FrameMatch` an id:

- People seen by two or more cameras have a triangulated skeleton. Each remembered person is
  moved forward by their velocity (constant-velocity model) and the two sets are matched by the
  Hungarian method on the median distance between corresponding landmarks, gated by a top speed.
  Landmark distances, not centres, decide: two players 0.3 m apart have centres 0.3 m apart,
  but each one's own skeleton moved only centimetres since the last frame.
- A single-view instance takes the id of a remembered person not seen in 3D this frame whose
  predicted skeleton, projected into that camera, fits its landmarks (someone walking out of
  the other cameras keeps their id); otherwise it continues the single-view instance in the
  same camera's previous frame that its box overlaps; otherwise it gets a new id.
- A person seen in 3D whom no remembered person explains continues, likewise, the single-view
  instance of the previous frame that one of their views overlaps (someone at the back whom a
  second camera starts to see keeps the id the first camera gave them).
- People unseen for more than `max_gap` processed frames are forgotten.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from calibration.camera import Camera, Rig
from gst.data.keypoints.instances import BODY_LANDMARKS, PersonInstance
from gst.data.keypoints.matching import (
    AssociationError,
    FrameMatch,
    MatchConfig,
    PersonGroup,
    camera_view,
    fit_errors,
)
from gst.detect.boxes import box_iou

_TORSO = np.array([11, 12, 23, 24])
_BODY = np.asarray(BODY_LANDMARKS)
_FAR = 1e6


@dataclass(frozen=True)
class TrackerConfig:
    max_speed: float = 10.0  # m/s: a landmark moving faster than this is someone else (sprint)
    slack: float = 0.12  # metres added to the speed gate (triangulation noise)
    max_gap: int = 15  # processed frames a person unseen is remembered
    view_error: float = 0.12  # single-view instance against a remembered person's projection
    box_iou: float = 0.3  # single-view instance against the previous frame's in that camera
    smoothing: float = 0.5  # weight of the newest velocity estimate
    confirm: int = 3  # frames seen in 3D before a person is used to predict (priors, 2D ids)
    # A person unseen for more than a frame is moved on by a velocity that fades with this
    # time constant (seconds; None: constant velocity): people in a crowd stop and turn, and a
    # prior that walks on leaves the person it stands for (docs/extract.md, "Lost in the
    # middle of a crowd")
    coast: float | None = 0.2
    # video frames between processed frames (extraction's frame_stride): `max_gap` and the one
    # processed step a prediction takes at full velocity count in processed frames
    frame_stride: int = 1
    # The velocity: of the torso's centre (shoulders and hips), averaged over about this many
    # seconds (None: of all body landmarks' centre, `smoothing` per frame). Limbs swing: at 30
    # fps a 3 cm wobble of the centre reads as 1 m/s
    velocity_time: float | None = 0.2

    def __post_init__(self):
        if self.frame_stride < 1:
            raise AssociationError(
                f"TrackerConfig.frame_stride must be >= 1, got {self.frame_stride}"
            )
        # written as `not ok` so that NaN, for which every comparison is False, is refused too
        if not (self.max_speed > 0 and self.slack >= 0 and self.max_gap >= 0):
            raise AssociationError(
                "TrackerConfig needs max_speed > 0, slack >= 0 and max_gap >= 0, got "
                f"{self.max_speed}, {self.slack}, {self.max_gap}"
            )
        if (self.coast is not None and not self.coast >= 0) or (
            self.velocity_time is not None and not self.velocity_time > 0
        ):
            raise AssociationError(
                "TrackerConfig needs coast >= 0 and velocity_time > 0 (or None), got "
                f"{self.coast}, {self.velocity_time}"
            )
        if not 0 < self.smoothing <= 1:
            raise AssociationError(
                f"TrackerConfig.smoothing must be in (0, 1], got {self.smoothing}"
            )


@dataclass
class _Track:
    pid: int
    skeleton: np.ndarray  # (33, 3) last known landmarks (NaN: never seen)
    velocity: np.ndarray  # (3,) metres per second
    frame_3d: int  # frame of `body`
    last_seen: int  # last frame with any view (3D or single)
    hits: int = 1  # frames seen in 3D

    def predict(
        self, frame: int, step: float, coast: float | None = None, stride: int = 1
    ) -> np.ndarray:
        """The skeleton moved on to `frame`: one processed step (`stride` frames of `step`
        seconds) at the last velocity, and beyond it (a person not seen since) a move that fades
        with time constant `coast` seconds, at most `coast` x the velocity (None: the velocity
        kept for ever)."""
        dt, one = (frame - self.frame_3d) * step, stride * step
        if coast is not None and dt > one:
            dt = one + (coast * -np.expm1(-(dt - one) / coast) if coast > 0 else 0.0)
        return self.skeleton + self.velocity * dt


def _centre(body: np.ndarray) -> np.ndarray | None:
    ok = np.all(np.isfinite(body), axis=1)
    return body[ok].mean(axis=0) if ok.any() else None


def skeleton_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Median distance between corresponding landmarks seen in both (B, 3); inf if none."""
    d = np.linalg.norm(a - b, axis=-1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else np.inf


@dataclass
class PersonIdTracker:
    """Stable ids for the people of consecutive frames of one capture (not thread-safe)."""

    rig: Rig | Sequence[Camera]
    step_seconds: float  # time between consecutive frame numbers
    config: TrackerConfig = field(default_factory=TrackerConfig)
    match_config: MatchConfig = field(default_factory=MatchConfig)
    _tracks: list[_Track] = field(default_factory=list)
    # per camera: (id, box, frame last seen) of the single-view people of the last `max_gap`
    # processed frames (only the last frame's were kept: a single-view person the detector
    # missed for one frame came back with a new id, every time)
    _single: dict[str, list[tuple[int, np.ndarray, int]]] = field(default_factory=dict)
    _next_id: int = 1
    _last_frame: int | None = None

    def __post_init__(self):
        cams = self.rig.cameras if isinstance(self.rig, Rig) else tuple(self.rig)
        self._cams = {c.name: c for c in cams}
        if not self.step_seconds > 0:
            raise AssociationError(f"step_seconds must be > 0, got {self.step_seconds}")

    def predict(self, frame: int) -> list[tuple[int, np.ndarray]]:
        """(id, (33, 3) predicted world skeleton) of the people remembered at `frame` (those seen
        in 3D within `max_gap` frames), moved on by their velocity: priors for `match_frame`."""
        return [
            (t.pid, self._moved_on(t, frame))
            for t in self._tracks
            if frame - t.last_seen <= self.config.max_gap * self.config.frame_stride
            and frame > t.frame_3d
            and t.hits >= self.config.confirm
        ]

    def _moved_on(self, t: _Track, frame: int) -> np.ndarray:
        return t.predict(frame, self.step_seconds, self.config.coast, self.config.frame_stride)

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def update(
        self,
        frame: int,
        match: FrameMatch,
        instances: Mapping[str, Sequence[PersonInstance]],
    ) -> list[int]:
        """Ids (>= 1) of `match.groups`, in order. Frames must come in increasing order."""
        if self._last_frame is not None and frame <= self._last_frame:
            raise AssociationError(
                f"frame {frame} comes after frame {self._last_frame}: the tracker needs frames "
                "in increasing order (make a new tracker to start again)"
            )
        self._last_frame = frame
        step = self.step_seconds
        gap = self.config.max_gap * self.config.frame_stride
        self._tracks = [t for t in self._tracks if frame - t.last_seen <= gap]
        ids = [0] * len(match.groups)
        multi = [g for g, grp in enumerate(match.groups) if grp.skeleton is not None]
        matched: set[int] = set()
        if multi and self._tracks:
            cost = np.full((len(multi), len(self._tracks)), _FAR)
            for r, g in enumerate(multi):
                body = match.groups[g].skeleton[_BODY]
                for c, t in enumerate(self._tracks):
                    dt = (frame - t.frame_3d) * step
                    d = skeleton_distance(body, self._moved_on(t, frame)[_BODY])
                    if d <= self.config.max_speed * dt + self.config.slack:
                        cost[r, c] = d
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] < _FAR:
                    ids[multi[r]] = self._tracks[c].pid
                    self._update_track(self._tracks[c], match.groups[multi[r]].skeleton, frame)
                    matched.add(c)
        for g in multi:
            if not ids[g]:
                sk = match.groups[g].skeleton.copy()
                pid = self._continued_single_view(match.groups[g], instances, ids)
                known = [c for c, t in enumerate(self._tracks) if t.pid == pid]
                if known:  # a remembered person whose single view went on: their 3D starts anew
                    t = self._tracks[known[0]]
                    t.skeleton, t.velocity, t.frame_3d, t.last_seen = sk, np.zeros(3), frame, frame
                    t.hits += 1
                    matched.add(known[0])
                else:
                    self._tracks.append(
                        _Track(pid or self._new_id(), sk, np.zeros(3), frame, frame)
                    )
                    matched.add(len(self._tracks) - 1)
                ids[g] = self._tracks[known[0] if known else -1].pid
        self._single_view_ids(frame, match, instances, ids, matched)
        return ids

    def _continued_single_view(
        self,
        group: PersonGroup,
        instances: Mapping[str, Sequence[PersonInstance]],
        ids: list[int],
    ) -> int | None:
        """The id of the previous frame's single-view instance that one of `group`'s views
        overlaps most (box IoU at least `box_iou`), if nobody has that id this frame."""
        best, best_iou = None, self.config.box_iou
        for cam_name, k in group.views.items():
            prev = [(pid, box) for pid, box, _ in self._single.get(cam_name, []) if pid not in ids]
            if not prev:
                continue
            iou = box_iou(instances[cam_name][k].box[None], np.stack([b for _, b in prev]))[0]
            j = int(np.argmax(iou))
            if iou[j] >= best_iou:
                best, best_iou = prev[j][0], float(iou[j])
        return best

    def _update_track(self, t: _Track, skeleton: np.ndarray, frame: int) -> None:
        dt = (frame - t.frame_3d) * self.step_seconds
        c = self.config
        part = _BODY if c.velocity_time is None else _TORSO
        old, new = _centre(t.skeleton[part]), _centre(skeleton[part])
        if old is not None and new is not None and dt > 0:
            a = c.smoothing if c.velocity_time is None else -np.expm1(-dt / c.velocity_time)
            t.velocity = a * (new - old) / dt + (1 - a) * t.velocity
        predicted = self._moved_on(t, frame)
        t.skeleton = np.where(np.isfinite(skeleton), skeleton, predicted)
        t.frame_3d = t.last_seen = frame
        t.hits += 1

    def _single_view_ids(
        self,
        frame: int,
        match: FrameMatch,
        instances: Mapping[str, Sequence[PersonInstance]],
        ids: list[int],
        matched: set[int],
    ) -> None:
        by_cam: dict[str, list[int]] = {}
        for g, grp in enumerate(match.groups):
            if grp.skeleton is None:
                by_cam.setdefault(next(iter(grp.views)), []).append(g)
        free = [
            c
            for c, t in enumerate(self._tracks)
            if c not in matched and t.hits >= self.config.confirm
        ]
        single: dict[str, list[tuple[int, np.ndarray, int]]] = {}
        for cam_name, gs in by_cam.items():
            insts = [instances[cam_name][match.groups[g].views[cam_name]] for g in gs]
            taken = np.zeros(len(gs), bool)
            # one person, one id per frame: a track whose id an earlier camera gave out (by fit,
            # or by box continuation below) is not free for this one (two single-view rows
            # shared an id and read as a two-view group)
            free = [t for t in free if self._tracks[t].pid not in ids]
            if free:
                view = camera_view(self._cams[cam_name], insts, self.match_config.min_confidence)
                pred = np.stack([self._moved_on(self._tracks[c], frame)[_BODY] for c in free])
                e, _ = fit_errors(pred, view, self.match_config)
                cost = np.where(e < self.config.view_error, e, _FAR)
                for r, c in zip(*linear_sum_assignment(cost), strict=True):
                    if cost[r, c] < _FAR:
                        ids[gs[c]] = self._tracks[free[r]].pid
                        self._tracks[free[r]].last_seen = frame
                        taken[c] = True
            prev = self._single.get(cam_name, [])
            if prev:
                todo = np.flatnonzero(~taken)
                if len(todo):
                    iou = box_iou(
                        np.stack([insts[k].box for k in todo]), np.stack([b for _, b, _ in prev])
                    )
                    cost = np.where(iou >= self.config.box_iou, -iou, _FAR)
                    for r, c in zip(*linear_sum_assignment(cost), strict=True):
                        if cost[r, c] < _FAR and prev[c][0] not in ids:
                            ids[gs[todo[r]]] = prev[c][0]
                            taken[todo[r]] = True
            for k in np.flatnonzero(~taken):
                ids[gs[k]] = self._new_id()
            single[cam_name] = [(ids[g], insts[k].box, frame) for k, g in enumerate(gs)]
        # the ones not seen this frame are remembered as long as a track is (`max_gap`)
        gap = self.config.max_gap * self.config.frame_stride
        for cam_name, entries in self._single.items():
            single.setdefault(cam_name, []).extend(
                e for e in entries if e[0] not in ids and frame - e[2] <= gap
            )
        self._single = single
