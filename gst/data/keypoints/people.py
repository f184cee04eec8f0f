"""The people of each frame of a calibrated multi-camera capture: ids, 3D skeletons, and in every
camera that sees them their landmarks and their own mask.

`CrowdTracker.process(frame, ...)` runs one frame, in frame order:

1. Match the cameras' person instances (a detector's, e.g. BlazePose per camera) into people
   (`match_frame`), with the people of the previous frames, moved on, as priors.
2. Remembered people that no group explains are kept as candidates (a person the detectors
   all missed in this frame is still there).
3. Look again at every person in every camera (`refine`): the landmark model is run on a
   region around their projected skeleton in which the pixels inside everyone else's capsules
   (`ownership.own_pixels`, `Ownership.covered`) are replaced by the empty background.
   With its neighbours painted out, the model finds the intended person even when half
   hidden (on the crowd preset: 98% of views at least 30% visible instead of 32% when the
   view is under 60% visible; truth occluders). Answers whose landmarks do not fit the
   projected skeleton are dropped; the rest re-triangulate the skeleton. Remembered people
   that fewer than two cameras confirm are let go for this frame. With `reuse_detections`,
   where no one else overlaps the person in a camera and their detection there fits the
   skeleton, that detection is their answer (on the lab capture 373 of 796 views).
4. Ids (`PersonIdTracker`), then per camera each person's mask: their region's segmentation
   within the foreground, pixels claimed by several people going to the one in front
   (capsule ownership). A trusted person (seen by `trusted_views` cameras, or remembered)
   that no camera's model confirmed but who is at least `project_visibility` visible there
   gets a mask from ownership alone and landmarks projected from the skeleton.

Single-view instances (one camera only) keep their own detection and mask. Before that, one who
stands apart from everyone else (`standing_apart`) is read as someone standing where their
ankles' ray meets the height of the triangulated people's ankles (`standing.standing_skeleton`)
and looked for in every camera like a remembered person: found in two, they are a person seen in
3D (the lab's bystander at the back, whom one camera's detector finds and another's does not).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from calibration.camera import Camera, Rig
from gst.data.keypoints.geometry import project
from gst.data.keypoints.instances import BODY_LANDMARKS, PersonInstance
from gst.data.keypoints.matching import (
    FrameMatch,
    MatchConfig,
    PersonGroup,
    _triangulate_all,
    camera_view,
    match_frame,
)
from gst.data.keypoints.ownership import OwnershipConfig, own_pixels
from gst.data.keypoints.regions import roi_from_skeleton, skeleton_fit
from gst.data.keypoints.standing import AnkleHeight, standing_skeleton
from gst.data.keypoints.tracking import PersonIdTracker, TrackerConfig, skeleton_distance
from gst.detect.blazepose import BodyRoi
from gst.detect.boxes import containment
from gst.detect.persons import same_person

log = logging.getLogger("gst.data")

_BODY = np.asarray(BODY_LANDMARKS)
PROJECTED_CONFIDENCE = 0.5  # confidence of landmarks projected from a skeleton (not detected)
STRAY_OVERLAP = 0.3  # a detection this much inside a person's box is near them
DUPLICATE_LANDMARKS = 0.1  # two answers whose limb joints are this close (share of size) agree
ViewSource = Literal["detected", "refined", "projected", "single"]
# segment(camera name, BGR image, region in its pixels, origin) -> (landmarks (33, 3) in the
# image's pixels, presence, (h, w) person probability) or None. The image is the window of the
# work-resolution frame that holds the region; origin = (x0, y0), its top-left pixel in the frame.
SegmentFn = Callable[
    [str, np.ndarray, BodyRoi, tuple[int, int]], tuple[np.ndarray, float, np.ndarray] | None
]


@dataclass(frozen=True)
class CrowdConfig:
    match: MatchConfig = field(default_factory=MatchConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    ownership: OwnershipConfig = field(default_factory=OwnershipConfig)
    refine: bool = True  # look again at every person with the others painted out
    refine_fit: float = 0.15  # landmark error (share of size) for a refined view to count
    # With reuse_detections, a view in which no one else overlaps the person (their capsules,
    # `Ownership.alone`) and whose detection fits the skeleton within reuse_fit (share of size)
    # keeps its detection as its refined view: the model is not run again there. Faster (lab
    # extraction 9 % less time), but in crowds it moves results both ways (docs/extract.md,
    # "Speed"), so it is off by default.
    reuse_detections: bool = False
    reuse_fit: float = 0.05
    min_presence: float = 0.5  # landmark model's presence score for a refined view
    occluder_margin: int = 2  # pixels the painted-out people are grown by
    # Looking again at a person, whose pixels are painted out: "covered", those inside another
    # person's capsules (`Ownership.covered`); "owned", every foreground pixel nearer to another
    # person's capsules than to theirs (before 2026-11-30). Where a person's skeleton has slid
    # off them, "owned" paints their own body out and the model answers where the skeleton
    # already is, so it never comes back (docs/extract.md, "Lost in the middle of a crowd")
    paint: Literal["covered", "owned"] = "covered"
    project_visibility: float = 0.3  # projected views for trusted people at least this visible
    trusted_views: int = 3  # cameras that must agree before a new person is trusted
    remembered_gap: float = 0.3  # a prior further than this (m) from every group is a candidate
    duplicate_gap: float = 0.15  # two candidates this close (m) after refinement are one person
    duplicate_hips: float = 0.1  # ... and two whose mid-hips lie this close (m; 0: not used)
    # ... and two whose mid-hips lie within `duplicate_near` (m) and whose refined views,
    # triangulated together, each fit that one skeleton at most `duplicate_fit` worse (mean
    # landmark error, share of the person's size; 0: not used) than their own (`_one_body`):
    # one person found from two sides, each triangulated from its own 3 views (crowd_7001:
    # 0.155 m apart, hips 0.114 m: a second id)
    duplicate_near: float = 0.4
    duplicate_fit: float = 0.03
    # the kept one of two such candidates takes the other's views in cameras it has none in
    merge_duplicates: bool = True
    min_mask_pixels: int = 20  # smaller masks are no view
    # look for a single-view person in the other cameras, where they would stand (see above)
    single_view_search: bool = True
    standing_fit: float = 0.3  # refine_fit for a view of such a guess (checked again after)
    # ... only for someone this far (m, along the floor) from every other person: in a crowd a
    # single view is mostly a part or a poor reading of someone, and the search there moved the
    # crowd scenes both ways by chance (docs/extract.md); the lab's bystander stands 3-5 m away
    standing_apart: float = 1.5

    def __post_init__(self):
        if self.standing_fit < self.refine_fit:
            raise ValueError(
                f"CrowdConfig needs standing_fit >= refine_fit, got {self.standing_fit}, "
                f"{self.refine_fit}"
            )
        if not 0 <= self.reuse_fit < self.refine_fit:
            raise ValueError(
                f"CrowdConfig needs 0 <= reuse_fit < refine_fit, got {self.reuse_fit}, "
                f"{self.refine_fit}"
            )
        if not 0 < self.project_visibility <= 1 or self.trusted_views < 2:
            raise ValueError(
                "CrowdConfig needs 0 < project_visibility <= 1 and trusted_views >= 2, got "
                f"{self.project_visibility}, {self.trusted_views}"
            )
        if self.duplicate_hips < 0 or self.duplicate_near < 0 or self.duplicate_fit < 0:
            raise ValueError(
                "CrowdConfig needs duplicate_hips, duplicate_near and duplicate_fit >= 0, got "
                f"{self.duplicate_hips}, {self.duplicate_near}, {self.duplicate_fit}"
            )


@dataclass(frozen=True)
class PersonView:
    """One person in one camera."""

    landmarks: np.ndarray  # (33, 3) u, v in distorted full-resolution pixels, confidence
    mask: np.ndarray  # (H, W) bool at the work resolution
    source: ViewSource
    visibility: float  # share of the person's capsules not hidden by others (NaN: unknown)


@dataclass(frozen=True)
class FramePerson:
    pid: int
    skeleton: np.ndarray | None  # (33, 3) world landmarks; None for a single-view person
    views: dict[str, PersonView]

    @property
    def single_view(self) -> bool:
        return self.skeleton is None


@dataclass(frozen=True)
class FramePeople:
    frame: int
    people: list[FramePerson]
    notes: list[str]


def _window(roi: BodyRoi, shape: tuple[int, ...], margin: int) -> tuple[int, int, int, int]:
    """Pixel bounds (x0, y0, x1, y1) within an image of `shape` of everything a (rotated)
    region can sample, `margin` pixels more for the interpolation."""
    half = 0.5 * roi.side * (abs(np.cos(roi.angle)) + abs(np.sin(roi.angle))) + margin
    cx, cy = roi.centre
    h, w = shape[:2]
    x0 = int(np.clip(np.floor(cx - half), 0, w))
    y0 = int(np.clip(np.floor(cy - half), 0, h))
    x1 = int(np.clip(np.ceil(cx + half) + 1, x0, w))
    y1 = int(np.clip(np.ceil(cy + half) + 1, y0, h))
    return x0, y0, x1, y1


def _detections(cands, n: str, instances, masks) -> dict[int, tuple[PersonInstance, np.ndarray]]:
    """Candidate index -> (their detection in camera `n`, its mask) for candidates matched
    there whose detection has a mask and holds no other detection that no candidate took (a
    stray fragment beside a person is told apart by looking again, as for everyone else)."""
    ms = (masks or {}).get(n)
    if ms is None:
        return {}
    taken = {c.group.views[n] for c in cands if c.group is not None and n in c.group.views}
    stray = [inst.box for i, inst in enumerate(instances[n]) if i not in taken]
    out = {}
    for k, c in enumerate(cands):
        i = None if c.group is None else c.group.views.get(n)
        if i is None or i >= len(ms) or ms[i] is None:
            continue
        box = instances[n][i].box
        if not any(containment(b, box) > STRAY_OVERLAP for b in stray):
            out[k] = (instances[n][i], ms[i])
    return out


def _projected_box(cam: Camera, skeleton: np.ndarray) -> np.ndarray | None:
    """(4,) extent of a world skeleton's projection into `cam` (None if nothing projects)."""
    uv, _ = project(cam, skeleton)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    return np.r_[uv.min(axis=0), uv.max(axis=0)] if len(uv) else None


def _hips(skeleton: np.ndarray) -> np.ndarray:
    """Mid-hip point (3,) of a (33, 3) world skeleton (NaN where a hip is unknown)."""
    return skeleton[[23, 24]].mean(axis=0)


def _strict_views(group: PersonGroup | None) -> int:
    return 0 if group is None else len(group.views) - len(group.loose)


@dataclass
class _Candidate:
    skeleton: np.ndarray
    remembered: bool
    group: PersonGroup | None
    refined: dict[str, tuple[PersonInstance, np.ndarray]] = field(default_factory=dict)
    fits: dict[str, float] = field(default_factory=dict)  # landmark error of each refined view
    single: PersonGroup | None = None  # the single-view group this candidate stands for


class CrowdTracker:
    """People of consecutive frames of one capture (keeps tracking state; one caller at a time).

    `scale` is the work resolution over the calibration's, one number or per camera (images,
    foregrounds and masks are at work resolution; landmarks and skeletons in full-resolution
    pixels and metres). `segment` runs the landmark model (None: no refinement); with
    `workers` > 1 the cameras of a frame are refined and masked on that many threads, so
    `segment` must then be thread-safe. The results do not depend on `workers`.
    """

    def __init__(
        self,
        rig: Rig | Sequence[Camera],
        step_seconds: float,
        config: CrowdConfig = CrowdConfig(),
        segment: SegmentFn | None = None,
        scale: float | Mapping[str, float] = 1.0,
        workers: int = 1,
    ):
        self.cams = {c.name: c for c in (rig.cameras if isinstance(rig, Rig) else rig)}
        up = rig.up if isinstance(rig, Rig) else (0.0, 0.0, 1.0)
        match, why = config.match.for_rig(list(self.cams.values()), up)
        if why is not None:
            log.warning("keypoint association: %s", why)
        config = replace(config, match=match)
        self.config = config
        self.segment = segment
        self.workers = max(1, int(workers))
        self._pool: ThreadPoolExecutor | None = None
        self.scale = {
            n: float(scale[n] if isinstance(scale, Mapping) else scale) for n in self.cams
        }
        self.ids = PersonIdTracker(
            list(self.cams.values()), step_seconds, config.tracker, config.match
        )
        self._kernel = np.ones((2 * config.occluder_margin + 1,) * 2, np.uint8)
        self._ankles = AnkleHeight(up)
        # refined views: the landmark model's new answer / the detection reused (`reuse_fit`)
        self.views_refined = self.views_reused = 0
        # single-view people looked for where they would stand / found by a second camera
        self.standing_tried = self.standing_found = 0

    def process(
        self,
        frame: int,
        instances: Mapping[str, Sequence[PersonInstance]],
        foreground: Mapping[str, np.ndarray],
        images: Mapping[str, np.ndarray] | None = None,
        backgrounds: Mapping[str, np.ndarray] | None = None,
        masks: Mapping[str, Sequence[np.ndarray | None]] | None = None,
    ) -> FramePeople:
        """One frame. `instances` and `foreground` (bool, work resolution) per camera; `images`
        (BGR, work resolution) and `backgrounds` (the empty scene, same size) are needed to
        refine; `masks[camera][i]` is instance i's own mask (used for single-view people)."""
        cfg = self.config
        for n, ms in (masks or {}).items():
            # masks pair with instances by index: a short list was an IndexError deep below
            if ms is not None and n in instances and len(ms) != len(instances[n]):
                raise ValueError(
                    f"frame {frame}, camera {n}: {len(ms)} masks for {len(instances[n])} "
                    "instances (masks[camera][i] is instance i's mask, None for none)"
                )
        priors = self.ids.predict(frame)
        match = match_frame(instances, list(self.cams.values()), cfg.match, [s for _, s in priors])
        cands = [_Candidate(g.skeleton, False, g) for g in match.groups if g.skeleton is not None]
        for _, sk in priors:
            if all(
                skeleton_distance(sk[_BODY], c.skeleton[_BODY]) > cfg.remembered_gap for c in cands
            ):
                cands.append(_Candidate(sk, True, None))
        # The foreground: the background model's, and wherever phase 1 found a person (a
        # background learnt from the capture itself misses people who stand still).
        foreground = dict(foreground)
        for n, ms in (masks or {}).items():
            if n in foreground and ms:
                foreground[n] = foreground[n] | np.any([m for m in ms if m is not None], axis=0)
        can_refine = cfg.refine and self.segment is not None and images is not None
        if can_refine and cfg.single_view_search:
            standing = self._standing(match, instances, cands)
            self.standing_tried += len(standing)
            cands += standing
        if can_refine and cands:
            self._refine(cands, foreground, images, backgrounds, instances, masks)
            # A person needs two confirming cameras, unless three detections agreed on them.
            cands = [
                c
                for c in cands
                if len(c.refined) >= 2
                or (not c.remembered and _strict_views(c.group) >= cfg.trusted_views)
            ]
            cands = self._distinct(cands)
        elif not can_refine:
            cands = [c for c in cands if not c.remembered]
        # Ids: one group per candidate (its refined views, else its matched ones) + singles.
        view_inst: dict[str, list[PersonInstance]] = {n: [] for n in self.cams}
        groups = []
        for c in cands:
            views = {}
            for n, (inst, _) in c.refined.items():
                views[n] = len(view_inst[n])
                view_inst[n].append(inst)
            if not views and c.group is not None:
                for n, k in c.group.views.items():
                    views[n] = len(view_inst[n])
                    view_inst[n].append(instances[n][k])
            groups.append(PersonGroup(views, c.skeleton, {}, {n: False for n in views}))
        if cfg.single_view_search:
            for c in cands:
                self._ankles.add(c.skeleton)
        found = {id(c.single) for c in cands if c.single is not None}
        self.standing_found += len(found)
        singles = [g for g in match.groups if g.skeleton is None and id(g) not in found]
        for g in singles:
            n, k = next(iter(g.views.items()))
            groups.append(PersonGroup({n: len(view_inst[n])}, None, {}, {n: False}))
            view_inst[n].append(instances[n][k])
        pids = self.ids.update(frame, FrameMatch(groups), view_inst)
        remembered = {pid for pid, _ in priors}
        people = [
            FramePerson(pid, c.skeleton, {})
            for c, pid in zip(cands, pids[: len(cands)], strict=True)
        ]
        names = [n for n in self.cams if n in foreground]

        # people only one camera sees, by their landmarks there: their pixels are theirs, not
        # the nearest 3D person's (a bystander 0.4 m from someone went into that one's mask)
        single_lms: dict[str, list[np.ndarray]] = {n: [] for n in self.cams}
        for g in singles:
            n, k = next(iter(g.views.items()))
            single_lms[n].append(instances[n][k].landmarks)

        def views_in(n: str) -> list[tuple[int, PersonView]]:
            return self._views(
                n, cands, people, foreground[n], remembered, instances, single_lms[n]
            )

        for n, views in zip(names, self._map_cameras(views_in, names), strict=True):
            for k, view in views:
                people[k].views[n] = view
        for g, pid in zip(singles, pids[len(cands) :], strict=True):
            n, k = next(iter(g.views.items()))
            m = masks[n][k] if masks is not None and masks.get(n) is not None else None
            if m is None or not np.any(m):
                continue
            # A detection of someone who already has a view here (a duplicate, or a
            # fragment the association did not take) is not another person.
            taken = [p.views[n].mask for p in people if n in p.views and p.skeleton is not None]
            if taken and np.count_nonzero(m & np.any(taken, axis=0)) > 0.5 * np.count_nonzero(m):
                continue
            people.append(
                FramePerson(
                    pid, None, {n: PersonView(instances[n][k].landmarks, m, "single", np.nan)}
                )
            )
        return FramePeople(frame, people, list(match.notes))

    def counts(self) -> list[str]:
        """What the optional paths did so far, one line each (for the log)."""
        cfg, lines = self.config, []
        if cfg.refine and cfg.reuse_detections:
            lines.append(
                f"{self.views_refined} views from the landmark model's second look; "
                f"{self.views_reused} views of people no one overlaps kept their detection "
                "(reuse_detections)"
            )
        if cfg.refine and cfg.single_view_search:
            lines.append(
                f"{self.standing_found} of {self.standing_tried} single-view people looked for "
                "where they would stand were found by a second camera"
            )
        return lines

    def _standing(self, match: FrameMatch, instances, cands) -> list[_Candidate]:
        """A candidate for each single-view person standing apart, where they would stand (none
        until the triangulated people have shown the ankles' height)."""
        cfg = self.config
        if self._ankles.value is None:  # the first frames: this frame's own triangulations
            for c in cands:
                self._ankles.add(c.skeleton)
        height = self._ankles.value
        if height is None:
            return []
        out, boxes = [], {}  # camera -> the candidates' projected boxes there
        for g in match.groups:
            if g.skeleton is not None:
                continue
            n, k = next(iter(g.views.items()))
            cam, inst = self.cams[n], instances[n][k]
            if n not in boxes:
                boxes[n] = [b for c in cands if (b := _projected_box(cam, c.skeleton)) is not None]
            # Only someone standing apart: a single view beside or over a candidate is mostly a
            # part or a poor reading of them, and looking there again would split their views.
            if any(containment(inst.box, box) > STRAY_OVERLAP for box in boxes[n]):
                continue
            sk = standing_skeleton(cam, inst, self._ankles.up, height, cfg.match.min_confidence)
            if sk is not None and all(
                self._floor_distance(_hips(sk), _hips(c.skeleton)) >= cfg.standing_apart
                for c in cands
            ):
                out.append(_Candidate(sk, False, None, single=g))
        return out

    def _floor_distance(self, a: np.ndarray, b: np.ndarray) -> float:
        """Distance (m) between two world points along the floor (NaN points: far)."""
        d = a - b
        d = d - (d @ self._ankles.up) * self._ankles.up
        n = float(np.linalg.norm(d))
        return n if np.isfinite(n) else np.inf

    def _distinct(self, cands: list[_Candidate]) -> list[_Candidate]:
        """One candidate per person: two whose skeletons converged (two regions that found the
        same person), or whose hips lie within `duplicate_hips` (two bodies cannot share their
        hips, whatever their limbs: the lab's man, kicking, was triangulated twice from different
        views with hips 2-4 cm apart and limbs 0.27-0.48 m apart), keep the one more cameras
        confirmed, which takes the other's views in cameras it has none in and is triangulated
        again from them all (`merge_duplicates`)."""
        cfg = self.config
        order = sorted(range(len(cands)), key=lambda k: (-len(cands[k].refined), k))
        hips = [_hips(c.skeleton) for c in cands]

        def same(k: int, j: int) -> bool:
            hip_gap = np.linalg.norm(hips[k] - hips[j])
            return bool(
                skeleton_distance(cands[k].skeleton[_BODY], cands[j].skeleton[_BODY])
                < cfg.duplicate_gap
                or hip_gap < cfg.duplicate_hips
                or (hip_gap < cfg.duplicate_near and self._one_body(cands[k], cands[j]))
            )

        keep: list[int] = []
        merged: set[int] = set()
        for k in order:
            twin = next((j for j in keep if same(k, j)), None)
            if twin is None:
                keep.append(k)
            elif cfg.merge_duplicates:
                # the person is seen in the views either found: the kept one takes the others'
                kept, other = cands[twin], cands[k]
                # in the views' own order (a set's order follows the process's hash seed, and
                # the re-triangulation below depends on the order)
                for n in [m for m in other.refined if m not in kept.refined]:
                    kept.refined[n], kept.fits[n] = other.refined[n], other.fits[n]
                    merged.add(twin)
        for j in merged:
            self._triangulate_refined(cands[j])
        return [cands[k] for k in sorted(keep)]

    def _map_cameras(self, fn, names: list[str]) -> list:
        """fn(name) for every camera, in order: on the worker threads when there are several
        (each camera's work is independent; numpy, OpenCV and LiteRT release the GIL)."""
        if self.workers <= 1 or len(names) <= 1:
            return [fn(n) for n in names]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="crowd")
        return list(self._pool.map(fn, names))

    def close(self) -> None:
        """Stop the worker threads (the tracker stays usable: they restart on demand)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def _refine(self, cands, foreground, images, backgrounds, instances, masks) -> None:
        cfg = self.config
        skels = [c.skeleton for c in cands]
        names = [n for n in self.cams if n in images and n in foreground]

        def one_camera(n: str) -> tuple[dict[int, tuple], int]:
            detected = _detections(cands, n, instances, masks) if cfg.reuse_detections else {}
            return self._refine_camera(
                n, cands, skels, foreground[n], images[n], backgrounds, detected
            )

        # Merged in camera order, whatever order the threads finished in.
        for n, (found, reused) in zip(names, self._map_cameras(one_camera, names), strict=True):
            self.views_reused += reused
            self.views_refined += len(found) - reused
            for k, (inst, prob, fit) in found.items():
                cands[k].refined[n] = (inst, prob)
                cands[k].fits[n] = fit
        for c in cands:
            self._triangulate_refined(c)
            if c.single is not None and len(c.refined) >= 2:
                for n in list(c.refined):  # each view against the triangulated skeleton
                    c.fits[n] = skeleton_fit(self.cams[n], c.refined[n][0], c.skeleton, cfg.match)
                    if c.fits[n] > cfg.refine_fit:
                        del c.refined[n], c.fits[n]

    def _one_body(self, a: _Candidate, b: _Candidate) -> bool:
        """Whether the refined views of `a` and `b` are one person's: triangulated together
        (each camera once, a's where both have one), every reading of either still fits that
        skeleton as a view joining a person does (`MatchConfig.view_error`) and at most
        `duplicate_fit` worse than its own candidate's skeleton. Two people side by side
        should not: the skeleton between them misses the readings of both (the figures and
        their caveat: docs/extract.md, "One person found from two sides")."""
        cfg = self.config
        views = {**b.refined, **a.refined}
        if cfg.duplicate_fit <= 0 or len(views) < 3 or not a.refined or not b.refined:
            return False
        min_conf = cfg.match.min_confidence
        cams = {n: camera_view(self.cams[n], [inst], min_conf) for n, (inst, _) in views.items()}
        X = _triangulate_all(cams, {n: (0, False) for n in views}, cfg.match)
        if np.count_nonzero(np.all(np.isfinite(X), axis=1)) < cfg.match.min_shared:
            return False
        for c in (a, b):
            for n, (inst, _) in c.refined.items():
                together = skeleton_fit(self.cams[n], inst, X, cfg.match)
                alone = skeleton_fit(self.cams[n], inst, c.skeleton, cfg.match)
                if not together <= min(cfg.match.view_error, alone + cfg.duplicate_fit):
                    return False
        return True

    def _triangulate_refined(self, c: _Candidate) -> None:
        """A candidate's skeleton from its refined views, where it has two or more."""
        if len(c.refined) >= 2:
            min_conf = self.config.match.min_confidence
            views = {
                n: camera_view(self.cams[n], [inst], min_conf) for n, (inst, _) in c.refined.items()
            }
            X = _triangulate_all(views, {n: (0, False) for n in c.refined}, self.config.match)
            c.skeleton = np.where(np.isfinite(X), X, c.skeleton)

    def _refine_camera(
        self, n, cands, skels, fg, img, backgrounds, detected
    ) -> tuple[dict[int, tuple], int]:
        """Camera `n`'s refined views (candidate index -> (instance, probability, fit)) and
        how many of them reuse the candidate's detection (`detected[k]`: their detection here
        and its mask) instead of running the model again."""
        cfg = self.config
        cam, s = self.cams[n], self.scale[n]
        own = own_pixels(cam, fg, skels, [], cfg.ownership, s, with_covered=cfg.paint == "covered")
        bg = (backgrounds or {}).get(n)
        found: dict[int, tuple] = {}
        reused: set[int] = set()
        for k, c in enumerate(cands):
            if k in detected and own.alone[k]:
                inst, mask = detected[k]
                fit = skeleton_fit(cam, inst, c.skeleton, cfg.match)
                if fit <= cfg.reuse_fit and inst.score >= cfg.min_presence:
                    found[k] = (inst, mask.astype(np.float32), fit)
                    reused.add(k)
                    continue
            theirs = own.covered if cfg.paint == "covered" else own.labels
            got = self._look(n, k, c, theirs, img, bg)
            if got is not None:
                found[k] = got
        # Two regions that found the same person: the view goes to whoever it fits best
        # (a candidate stitched from two people loses the views that are someone else's).
        holders = list(found)
        for i, a in enumerate(holders):
            for b in holders[i + 1 :]:
                if a not in found or b not in found:
                    continue
                if same_person(found[a][0].landmarks, found[b][0].landmarks, DUPLICATE_LANDMARKS):
                    # a single-view person's guessed place never takes a view from the others
                    guess_a, guess_b = cands[a].single is not None, cands[b].single is not None
                    if guess_a != guess_b:
                        del found[a if guess_a else b]
                    else:
                        del found[b if found[a][2] <= found[b][2] else a]
        return found, len(reused & set(found))

    def _look(self, n, k, c, theirs, img, bg) -> tuple | None:
        """Candidate `k`'s answer (instance, probability, fit) from the landmark model in camera
        `n` on the region around their projected skeleton, with the other people's pixels of
        `theirs` (a label image: person index + 1) painted over with the empty scene `bg`, or
        None where the model finds nobody there who fits the skeleton."""
        cfg, cam, s = self.config, self.cams[n], self.scale[n]
        roi = roi_from_skeleton(cam, c.skeleton)
        if roi is None:
            return None
        centre = ((roi.centre[0] + 0.5) * s - 0.5, (roi.centre[1] + 0.5) * s - 0.5)
        work_roi = BodyRoi(centre, roi.side * s, roi.angle)
        # The model sees only the region: paint and pass the window that holds it (far
        # cheaper than a painted copy of the whole frame per person and camera).
        x0, y0, x1, y1 = _window(work_roi, img.shape, 2)
        if x1 - x0 < 2 or y1 - y0 < 2:  # the region lies outside the image
            return None
        m = cfg.occluder_margin
        g0, h0 = max(x0 - m, 0), max(y0 - m, 0)
        grown = theirs[h0 : y1 + m, g0 : x1 + m]
        others = cv2.dilate(((grown > 0) & (grown != k + 1)).astype(np.uint8), self._kernel)
        others = others[y0 - h0 : y0 - h0 + y1 - y0, x0 - g0 : x0 - g0 + x1 - x0] > 0
        window = img[y0:y1, x0:x1]
        fill = bg[y0:y1, x0:x1] if bg is not None else np.full_like(window, 128)
        painted = np.where(others[..., None], fill, window)
        cx, cy = work_roi.centre
        got = self.segment(
            n, painted, BodyRoi((cx - x0, cy - y0), work_roi.side, roi.angle), (x0, y0)
        )
        if got is None:
            return None
        lm, presence, prob_window = got
        if not presence >= cfg.min_presence:  # a NaN presence is no answer either
            return None
        prob = np.zeros(img.shape[:2], np.float32)
        prob[y0:y1, x0:x1] = prob_window
        lm = np.asarray(lm, np.float64).copy()
        # window -> work image -> full resolution, pixel centres at integers in both (as phase
        # 1 maps them; u / s put every refined view 0.5 px up-left at half resolution)
        lm[:, :2] = (lm[:, :2] + (x0, y0) + 0.5) / s - 0.5
        inst = PersonInstance.create(lm, None, presence, where=f"camera {n}, refined")
        fit = skeleton_fit(cam, inst, c.skeleton, cfg.match)
        # a standing guess is only as good as the body's depth: a looser gate to find them,
        # the usual one against the skeleton triangulated from what was found (_refine)
        if fit > (cfg.standing_fit if c.single is not None else cfg.refine_fit):
            return None
        return inst, prob, fit

    def _views(
        self, n, cands, people, fg, remembered, instances, singles=()
    ) -> list[tuple[int, PersonView]]:
        """Each person's view in camera `n`, as (person index, view): refined (their region's
        segmentation, contested pixels to the one in front), detected (ownership of the
        foreground, the detector's landmarks), or projected (ownership, projected landmarks)
        for trusted people. `singles`: (33, 3) landmarks of the people only this camera sees,
        who own their pixels too (behind every 3D person where they overlap)."""
        cfg, cam = self.config, self.cams[n]
        out = []
        skeletons = [c.skeleton for c in cands] + [None] * len(singles)
        flat = [None] * len(cands) + list(singles)
        own = own_pixels(cam, fg, skeletons, flat, cfg.ownership, self.scale[n])
        # A refined view's mask is the landmark model's own segmentation of that person.
        claims = [c.refined[n][1] > 0.5 if n in c.refined else None for c in cands]
        drawn = [m for m in claims if m is not None]
        contested = np.sum(drawn, axis=0) > 1 if drawn else np.zeros_like(fg)
        for k, (c, person) in enumerate(zip(cands, people, strict=True)):
            if claims[k] is not None:
                mask = claims[k] & (~contested | (own.labels == k + 1))
                lm, source = c.refined[n][0].landmarks, "refined"
            elif c.group is not None and n in c.group.views:
                mask = own.labels == k + 1
                lm, source = instances[n][c.group.views[n]].landmarks, "detected"
            else:
                strict = _strict_views(c.group)
                trusted = (
                    c.remembered
                    or person.pid in remembered
                    or max(strict, len(c.refined)) >= cfg.trusted_views
                )
                if not trusted or own.visibility[k] < cfg.project_visibility:
                    continue
                mask = own.labels == k + 1
                uv, _ = project(cam, c.skeleton)
                conf = np.where(np.all(np.isfinite(uv), axis=1), PROJECTED_CONFIDENCE, 0.0)
                lm, source = np.c_[np.nan_to_num(uv), conf], "projected"
            if np.count_nonzero(mask) >= cfg.min_mask_pixels:
                out.append((k, PersonView(lm, mask, source, float(own.visibility[k]))))
        return out
