"""Person instance masks for a frame: BlazePose regions from detection, hints and tracking.

`PersonSegmenter.segment(frame, hints)` gathers regions of interest from three sources: the
detector, boxes supplied by the caller (e.g. background-subtraction blobs, which find moving
people the detector misses), and the previous frame's people (their landmarks predict where
they are now, as MediaPipe tracks). The landmark model segments each region; regions whose
person is absent are dropped, duplicates of the same person are merged, and every pixel goes to
the person with the highest probability above the threshold. The result is a uint8 label
image in the same convention as `gst.data.masks.clean_mask` (1..n, largest person first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gst.detect.blazepose import (
    BlazePose,
    BodyRoi,
    PersonSegment,
    ZoomedScan,
    as_bgr_frame,
    roi_from_alignment,
    roi_from_box,
    same_region,
)
from gst.detect.boxes import box_iou, paint_out, pixel_window, shared

# BlazePose's 33 landmarks: the bones drawn to bound a person's mask (limbs, hands, feet).
BONES = (
    (11, 13),
    (13, 15),
    (12, 14),
    (14, 16),
    (15, 17),
    (15, 19),
    (15, 21),
    (16, 18),
    (16, 20),
    (16, 22),
    (11, 23),
    (12, 24),
    (23, 25),
    (25, 27),
    (24, 26),
    (26, 28),
    (27, 29),
    (29, 31),
    (27, 31),
    (28, 30),
    (30, 32),
    (28, 32),
)
TORSO = (11, 12, 24, 23)  # shoulders and hips
HEAD = (0, 7, 8)  # nose and ears


def _draw_skeleton(canvas: np.ndarray, pts: np.ndarray, value: int, thickness: int) -> None:
    """Bones, the torso outline and the head-to-neck line of int landmarks `pts`, in place."""
    for a, b in BONES + tuple(zip(TORSO, TORSO[1:] + TORSO[:1], strict=True)):
        cv2.line(
            canvas, tuple(map(int, pts[a])), tuple(map(int, pts[b])), value, thickness=thickness
        )
    head = tuple(map(int, pts[list(HEAD)].mean(axis=0)))
    cv2.line(canvas, head, tuple(map(int, (pts[11] + pts[12]) // 2)), value, thickness=thickness)


def skeleton_support(landmarks: np.ndarray, shape: tuple[int, int], width: float) -> np.ndarray:
    """Boolean (H, W) region within `width` pixels of a person's skeleton: thick bones, the filled
    torso and the head. The landmark model segments everyone in its region; keeping only the
    pixels near this person's own skeleton stops one person's mask from swallowing a neighbour."""
    out = np.zeros(shape, np.uint8)
    pts = np.round(landmarks[:, :2]).astype(np.int32)
    t = max(1, int(round(width)))
    _draw_skeleton(out, pts, 1, 2 * t)
    cv2.fillConvexPoly(out, pts[list(TORSO)], 1)
    head_r = max(t, int(round(np.linalg.norm(landmarks[7, :2] - landmarks[8, :2]))))
    cv2.circle(
        out,
        tuple(map(int, pts[list(HEAD)].mean(axis=0))),
        int(round(head_r * 1.2)) + t,
        1,
        thickness=-1,
    )
    return out.astype(bool)


@dataclass(frozen=True)
class SegmenterConfig:
    # What a region's answer must be to count as a person, and their mask.
    min_presence: float = 0.5  # landmark model's presence score needed to keep a region
    threshold: float = 0.5  # person probability for a pixel to belong to someone
    # Two regions found the same person when their limb joints lie this close (share of body size).
    duplicate_distance: float = 0.15
    min_area: float = 0.001  # smallest person mask, as a share of the image area
    # Mask pixels must lie within this share of the region's side of the person's own skeleton.
    skeleton_width: float = 0.08
    # Where regions come from: the previous frame's people, the detector, and hint boxes.
    track: bool = True  # seed each frame with the previous frame's people
    # With tracking: frames between runs of the person detector while every tracked person is
    # still found (it runs at once when one is lost, and when nobody is tracked); 1: every
    # frame. Extraction passes 10 (`extract.person_detect_every`): on the lab capture the same
    # 800 crops and 2 ids, and as accurate on the demo and crowd scenes together with the hint
    # memory below (docs/person_models.md).
    detect_every: int = 1
    # a detector region this close to a tracked person's (share of the side) is that person
    same_region: float = 0.1
    # A hint box is segmented only if people found without hints cover less than this share of it.
    hint_covered: float = 0.3
    # frames before a hint box where the landmark model found nobody is looked at again (1:
    # every frame). A still shadow or reflection stays a background blob for the whole clip; a
    # person the detector missed moves, and a moved box is a new hint at once.
    hint_retry: int = 10
    # a hint box overlapping a fruitless one by this intersection over union is the same box
    same_hint: float = 0.5
    # With each detector run, look once more with the people found painted out, in squares of
    # this share of the shorter side (`blazepose.zoomed_windows`; 0: not), `zoom_per_run` of
    # them in turn: people too small for the detector's usual windows are larger there (the
    # lab's bystander at the back of cam02). What is found only there is kept when its limbs
    # lie in the frame and are sure (`whole_and_sure`, `zoom_min_confidence`): up close, an
    # anatomical skeleton model or a camera mount also looks like a person.
    zoom: float = 0.0
    zoom_per_run: int = 3
    zoom_min_confidence: float = 0.75
    # ... and when its landmarks' box shares at most this much (of the smaller box) with a
    # person found before: where it overlaps one, it is a part of them (a raised arm reaching
    # out of their painted box)
    zoom_overlap: float = 0.3

    def __post_init__(self):
        for name in ("min_presence", "threshold", "hint_covered"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"segmenter {name} must be in (0, 1), got {getattr(self, name)}")
        for name in ("detect_every", "hint_retry"):
            if getattr(self, name) < 1:
                raise ValueError(f"segmenter {name} must be >= 1, got {getattr(self, name)}")
        if (
            not 0 <= self.zoom < 1
            or self.zoom_per_run < 1
            or not 0 <= self.zoom_min_confidence <= 1
            or not 0 <= self.zoom_overlap <= 1
        ):
            raise ValueError(
                f"segmenter zoom in [0, 1), zoom_per_run >= 1, zoom_min_confidence and "
                f"zoom_overlap in [0, 1] expected, got {self.zoom}, {self.zoom_per_run}, "
                f"{self.zoom_min_confidence}, {self.zoom_overlap}"
            )
        if not 0 < self.same_hint <= 1:
            raise ValueError(f"segmenter same_hint must be in (0, 1], got {self.same_hint}")
        if self.duplicate_distance <= 0:
            raise ValueError(
                f"segmenter duplicate_distance must be > 0, got {self.duplicate_distance}"
            )


LIMB_JOINTS = [11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28]  # shoulders .. ankles


def body_size(landmarks: np.ndarray) -> float:
    """Diagonal of the limb joints' box, in pixels: the scale for comparing two skeletons."""
    j = landmarks[LIMB_JOINTS, :2]
    return float(np.hypot(*(j.max(axis=0) - j.min(axis=0))))


def whole_and_sure(landmarks: np.ndarray, shape: tuple[int, int], min_confidence: float) -> bool:
    """Whether a person's 12 limb landmarks (x, y, confidence) all lie in the (H, W) image and
    their median confidence is at least `min_confidence`: what someone found by looking again
    (zoomed in, or with the people found painted out) must be, when found and in their own region
    the next frame. Up close, things that look like a person are found too, and on the lab
    capture those were cut by the frame's edge in some regions (an anatomical skeleton model, a
    camera mount on the wall: limb landmarks up to 160 px outside) or unsure in their own
    (confidence 0.01-0.72), while the small people at the back it is for stand whole in the
    frame and are sure of their limbs (0.82-1.0)."""
    h, w = shape
    limbs = landmarks[LIMB_JOINTS]
    inside = (
        (limbs[:, 0] >= 0) & (limbs[:, 0] <= w - 1) & (limbs[:, 1] >= 0) & (limbs[:, 1] <= h - 1)
    )
    return bool(inside.all()) and float(np.median(limbs[:, 2])) >= min_confidence


def look_twice(
    results: list, look, min_presence: float, shape: tuple[int, int], min_confidence: float
) -> list:
    """`results` (each with `presence`, `landmarks` and `next_roi`), with those whose person is
    absent (presence below `min_presence`) although their limbs stand whole and sure in the
    (H, W) image (`whole_and_sure`) replaced by `look([their next_roi, ...])`'s answers.

    A detector hit far away is a small region, often off the person's centre, where the landmark
    model may doubt a person it has placed well, while the region it predicts from them frames
    them (the lab's bystander at the back of cam02: presence 0.10-0.22 in the hit's region,
    1.00 in the one it predicted). Her detection hung on that before: a shift of a pixel or two
    in the painted-out boxes took her presence from 0.94 to 0.22 (docs/person_models.md). What
    is unsure of its limbs is not looked at again: the lab's anatomical skeleton model (presence
    0.06, median limb confidence 0.66) reads as a person in the region it predicts (0.84)."""
    low = [
        i
        for i, r in enumerate(results)
        if r.presence < min_presence and whole_and_sure(r.landmarks, shape, min_confidence)
    ]
    if not low:
        return results
    out = list(results)
    for i, again in zip(low, look([results[i].next_roi for i in low]), strict=True):
        out[i] = again
    return out


def same_person(a: np.ndarray, b: np.ndarray, distance: float) -> bool:
    """Whether two landmark sets describe one person: median limb-joint distance below
    `distance` x the smaller body size. (Masks cannot tell: people who overlap in the image
    have overlapping masks, and the landmark model segments everyone in its region.)"""
    d = np.linalg.norm(a[LIMB_JOINTS, :2] - b[LIMB_JOINTS, :2], axis=1)
    return float(np.median(d)) < distance * max(min(body_size(a), body_size(b)), 1.0)


def _skeleton_distance(
    landmarks: np.ndarray, shape: tuple[int, int], origin: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """Distance (px) of every pixel of the (H, W) `shape` window at `origin` (x, y) of the image
    to a person's skeleton lines."""
    lines = np.full(shape, 255, np.uint8)
    pts = np.round(landmarks[:, :2] - np.asarray(origin, np.float64)).astype(np.int32)
    _draw_skeleton(lines, pts, 0, 1)
    return cv2.distanceTransform(lines, cv2.DIST_L2, 3)


def _window(masks: Sequence[np.ndarray], skeletons: Sequence[np.ndarray]) -> tuple[slice, slice]:
    """The image window (rows, columns) that holds every mask pixel and every in-image pixel of
    the skeletons' lines. A line lies within its ends' box, so the box of the ends clipped to
    the image holds its in-image pixels: the skeleton distances computed in the window are those
    of the whole image wherever a mask is."""
    h, w = masks[0].shape
    union = np.logical_or.reduce(masks)
    rows, cols = np.flatnonzero(union.any(axis=1)), np.flatnonzero(union.any(axis=0))
    pts = np.concatenate([np.round(s[:, :2]) for s in skeletons])
    pts = np.clip(np.nan_to_num(pts), 0, (w - 1, h - 1)).astype(int)
    y0, y1 = min(rows[0], pts[:, 1].min()), max(rows[-1], pts[:, 1].max()) + 1
    x0, x1 = min(cols[0], pts[:, 0].min()), max(cols[-1], pts[:, 0].max()) + 1
    return slice(int(y0), int(y1)), slice(int(x0), int(x1))


def distinct_people(
    segments: Sequence[PersonSegment], config: SegmenterConfig, image_area: int
) -> list[PersonSegment]:
    """The segments that are distinct people, most confident first: the person is present,
    the mask is big enough and the skeleton does not repeat a kept, more confident one."""
    cands = [s for s in segments if s.presence >= config.min_presence]
    areas = [int(np.count_nonzero(s.probability > config.threshold)) for s in cands]
    order = sorted(range(len(cands)), key=lambda i: (-round(cands[i].presence, 2), -areas[i]))
    kept: list[PersonSegment] = []
    for i in order:
        if areas[i] < config.min_area * image_area or any(
            same_person(cands[i].landmarks, k.landmarks, config.duplicate_distance) for k in kept
        ):
            continue
        kept.append(cands[i])
    return kept


def compose_instances(
    segments: Sequence[PersonSegment], config: SegmenterConfig, image_area: int
) -> tuple[np.ndarray | None, list[PersonSegment]]:
    """Label image (1..n, largest first) of the distinct people among `segments`
    (`distinct_people`), and those people.

    A pixel that some kept person's mask claims goes to the claimant whose skeleton is nearest,
    which splits people who overlap in the image. Returns (None, []) when nobody is kept.
    """
    kept = distinct_people(segments, config, image_area)
    if not kept:
        return None, []
    masks = [k.probability > config.threshold for k in kept]
    if not any(m.any() for m in masks):  # (only with min_area 0)
        return np.zeros(masks[0].shape, np.uint8), []
    # Only the pixels that someone claims get a label: work in the window that holds them.
    rows, cols = _window(masks, [k.landmarks for k in kept])
    claimed = np.stack([m[rows, cols] for m in masks])
    origin = (cols.start, rows.start)
    dist = np.stack([_skeleton_distance(k.landmarks, claimed.shape[1:], origin) for k in kept])
    best = np.where(claimed, dist, np.inf).argmin(axis=0)
    owned = claimed.any(axis=0)
    areas = np.bincount(best[owned], minlength=len(kept))
    rank = np.argsort(-areas, kind="stable")  # label 1 = largest person
    lut = np.zeros(len(kept), dtype=np.uint8)
    lut[rank] = np.arange(1, len(kept) + 1, dtype=np.uint8)
    labels = np.zeros(masks[0].shape, np.uint8)
    labels[rows, cols] = np.where(owned, lut[best], 0)
    # A person whose whole mask went to others is not in the image. Their area is 0, so they
    # rank last and the labels of the others are already 1..m.
    people = [kept[r] for r in rank if areas[r] > 0]
    return labels, people


def _landmark_box(landmarks: np.ndarray) -> np.ndarray:
    """Corner box (x0, y0, x1, y1) of a person's landmarks (`paint_out` grows it)."""
    xy = landmarks[:, :2]
    return np.r_[xy.min(axis=0), xy.max(axis=0)]


def _corners(boxes) -> np.ndarray:
    """(N, 4) x, y, w, h boxes -> (N, 4) x0, y0, x1, y1."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    return np.c_[b[:, :2], b[:, :2] + b[:, 2:]]


class PersonSegmenter:
    """Instance masks of the people in a stream of frames from one camera (keeps tracking state)."""

    def __init__(self, model: BlazePose, config: SegmenterConfig = SegmenterConfig()):
        self.model = model
        self.config = config
        self._tracked: list[BodyRoi] = []
        self._since_detect = 0
        # hint boxes where nobody was found: (x, y, w, h) -> frames until they are looked at again
        self._fruitless: dict[tuple[float, float, float, float], int] = {}
        self.detector_runs = 0  # frames on which the person detector ran (for benchmarks)
        self.hint_regions = 0  # hint regions given to the landmark model (for benchmarks)
        self.zoom_found = 0  # people kept from the zoomed look (for benchmarks)
        self._zoom = ZoomedScan(config.zoom, config.zoom_per_run)
        self._probation: set[BodyRoi] = set()  # next regions of the zoomed look's new finds

    def reset(self) -> None:
        self._tracked, self._since_detect, self._fruitless = [], 0, {}
        self._zoom.reset()
        self._probation = set()

    def _zoomed_look(
        self, frame: np.ndarray, segments: list[PersonSegment], rois: list[BodyRoi]
    ) -> list[PersonSegment]:
        """Segments of the people found in the next zoomed windows with everyone in `segments`
        painted out (`SegmenterConfig.zoom`)."""
        c = self.config
        h, w = frame.shape[:2]
        windows = self._zoom.next(w, h)
        people = distinct_people(segments, c, h * w)
        boxes = [_landmark_box(p.landmarks) for p in people]
        hits = self.model.detect(paint_out(frame, boxes), windows)
        found = [roi_from_alignment(d.keypoints[0], d.keypoints[1]) for d in hits]
        new = [f for f in found if not any(same_region(f, r, c.same_region) for r in rois)]
        segments = look_twice(
            self._segment_rois(frame, new),
            lambda again: self._segment_rois(frame, again),
            c.min_presence,
            (h, w),
            c.zoom_min_confidence,
        )
        return [
            s
            for s in segments
            if whole_and_sure(s.landmarks, (h, w), c.zoom_min_confidence)
            and all(shared(_landmark_box(s.landmarks), b) <= c.zoom_overlap for b in boxes)
        ]

    def _segment_rois(self, frame: np.ndarray, rois: Sequence[BodyRoi]) -> list[PersonSegment]:
        h, w = frame.shape[:2]
        out = []
        for roi in rois:
            seg = self.model.segment(frame, roi)
            if self.config.skeleton_width > 0:
                near = skeleton_support(
                    seg.landmarks, (h, w), self.config.skeleton_width * roi.side
                )
                seg = replace(
                    seg, probability=np.where(near, seg.probability, 0.0).astype(np.float32)
                )
            out.append(seg)
        return out

    def _uncovered(self, labels, hints, shape: tuple[int, int]) -> list:
        """The hint boxes that the people in `labels` (None: nobody) cover less than
        `hint_covered` of."""
        found = labels > 0 if labels is not None else np.zeros(shape, bool)
        out = []
        for x, y, bw, bh in hints:
            window = pixel_window((x, y, x + bw, y + bh), found.shape)
            if window is not None and found[window].mean() < self.config.hint_covered:
                out.append((x, y, bw, bh))
        return out

    def segment(
        self, frame: np.ndarray, hints: Sequence[tuple[float, float, float, float]] = ()
    ) -> tuple[np.ndarray, list[PersonSegment]]:
        """Label image (uint8, 0 = nobody) and the people found in a BGR frame.

        `hints` are x, y, w, h boxes that may hold a person (e.g. moving blobs). They are looked
        at after the detector and tracking, and only where those found nobody; a hint's region
        is at least as big as the people already found (a blob may be a fragment of a body).
        """
        frame = as_bgr_frame(frame)  # (a grey frame failed in the zoomed look's paint-out)
        h, w = frame.shape[:2]
        c = self.config
        tracked = self._tracked if c.track else []
        segments = self._segment_rois(frame, tracked)
        # someone found zoomed in is confirmed only where their own region still shows a whole
        # person, sure of their limbs (an anatomical skeleton model is not, there)
        segments = [
            s
            if r not in self._probation
            or whole_and_sure(s.landmarks, (h, w), c.zoom_min_confidence)
            else replace(s, presence=0.0)
            for r, s in zip(tracked, segments, strict=True)
        ]
        lost = sum(s.presence >= c.min_presence for s in segments) < len(tracked)
        rois = list(tracked)
        zoomed: set[BodyRoi] = set()
        if not tracked or lost or self._since_detect + 1 >= c.detect_every:
            self._since_detect = 0
            self.detector_runs += 1
            detected = [
                roi_from_alignment(d.keypoints[0], d.keypoints[1]) for d in self.model.detect(frame)
            ]
            # a detection of a tracked person is that person's region again: not segmented twice
            new = [
                r for r in detected if not any(same_region(r, t, c.same_region) for t in tracked)
            ]
            segments += self._segment_rois(frame, new)
            rois += new
            if c.zoom > 0:
                more = self._zoomed_look(frame, segments, rois)
                self.zoom_found += len(more)
                segments += more
                rois += [m.next_roi for m in more]
                zoomed = {m.next_roi for m in more}
        else:
            self._since_detect += 1
        labels, people = compose_instances(segments, self.config, h * w)
        self._fruitless = {b: n - 1 for b, n in self._fruitless.items() if n > 1}
        if hints:
            sides = [r.side for r in rois]
            floor = float(np.median(sides)) if sides else 0.0
            boxes = self._uncovered(labels, hints, (h, w))
            if boxes and self._fruitless:
                seen = box_iou(_corners(boxes), _corners(list(self._fruitless))).max(axis=1)
                boxes = [b for b, v in zip(boxes, seen, strict=True) if v < c.same_hint]
            extra = []
            for box in boxes:
                roi = roi_from_box(box)
                extra.append(replace(roi, side=max(roi.side, floor)))
            if extra:
                self.hint_regions += len(extra)
                found = self._segment_rois(frame, extra)
                labels, people = compose_instances(segments + found, self.config, h * w)
                kept = {id(p) for p in people}
                for box, seg in zip(boxes, found, strict=True):
                    if id(seg) not in kept and c.hint_retry > 1:
                        self._fruitless[tuple(box)] = c.hint_retry
        self._tracked = [p.next_roi for p in people]
        self._probation = zoomed & set(self._tracked)
        if labels is None:
            return np.zeros((h, w), np.uint8), []
        return labels, people
