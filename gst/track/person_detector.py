"""`PersonModelDetector`: people from the learned BlazePose models (gst.detect), tracked with the
landmark model's own loop, as MediaPipe does.

Each person found in one frame gives the next frame's region of interest (from their alignment
landmarks), and the landmark model alone follows them there: one batched call per frame for
everybody. The person detector (several windows over the frame, the expensive part) runs only
when it is needed: on the first frame, when a tracked person is lost (presence below
`min_presence`), when nobody is tracked, and every `detect_every` processed frames to find new
arrivals. Its detections that repeat a tracked person are dropped before the landmark model
(same region) or after it (same skeleton, `gst.detect.persons.same_person`). The detector was made
for one person and returns few per call, so each time it runs it looks once more with everyone
already found painted out (`look_again`); a person it finds then is kept only where their box
barely overlaps anyone's (`look_again_overlap`): where two overlap, the landmark model's loop
could not keep them apart (docs/track_evaluation.md, "Looking again"). That second look also
scans zoomed-in windows, where people far at the back are larger (`look_again_zoom`), and what it
finds stays only once its own region, the next frame, shows a whole person sure of their limbs
(docs/track_evaluation.md, "Small people at the back").

A person the landmark model loses, often one walking behind another with their head hidden (the
detector finds people by the face), is looked for again in their last region for `lost_retry`
frames, on a copy of the frame with everyone tracked painted out by their own masks; found there,
they are followed on such a copy while they overlap someone (docs/track_evaluation.md, "Lost
behind someone").

A person who stands still is not looked at again (`still_change`): where a 32 x 32 thumbnail of
their mask's box (grown by a tenth) has barely changed since the frame their landmarks were
computed on (99 % of its pixels within `still_change` grey levels), those landmarks are theirs in
this frame too, and the landmark model skips them, up to `still_refresh` frames in a row
(docs/track_evaluation.md, "People who stand still").

Every detection carries the person's 33 landmarks (full-frame pixels, pixel centres at
integers, confidence = visibility x presence) and the box of their mask: the landmark model's
segmentation in the region's own crop, kept within `skeleton_width` of the person's skeleton
(the model segments everyone in its region), mapped back to the frame. Work happens at a work
resolution (longer side `max_side`, one resize per frame). Frames must come in order; a frame
index that goes back, or jumps forward by more than `max_gap`, restarts from the detector.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from gst.detect.blazepose import (
    LANDMARK_SIZE,
    BatchedLandmarks,
    BlazePose,
    BodyRoi,
    RegionLandmarks,
    ZoomedScan,
    as_bgr_frame,
    roi_from_alignment,
    same_region,
)
from gst.detect.boxes import fill_where, mean_colour, paint_out, shared
from gst.detect.persons import (
    LIMB_JOINTS,
    look_twice,
    same_person,
    skeleton_support,
    whole_and_sure,
)
from gst.track.detection import Detection


@dataclass(frozen=True)
class PersonModelConfig:
    max_side: int = 960  # work resolution: longer side in pixels
    detect_every: int = 10  # processed frames between detector runs while everyone is tracked
    min_presence: float = 0.5  # landmark model presence needed to keep a person
    duplicate_distance: float = 0.15  # same person: median limb-joint distance / body size
    skeleton_width: float = 0.08  # mask pixels within this share of the region of the skeleton
    min_height_frac: float = 0.08  # boxes shorter than this share of the frame height are dropped
    same_region: float = 0.1  # a detector region this close to a kept person's (share of the
    # side) is that person: not run through the landmark model again
    max_gap: int = 5  # a forward jump of more frames than this restarts from the detector
    # The person detector returns few people per call (it was made for one): each time it runs,
    # it looks once more with everyone already found painted out, so that a second person in
    # plain view is not left waiting for a detector run that happens to pick them first
    look_again: bool = True
    look_again_overlap: float = 0.3  # ... keeping a person whose box shares at most this much
    # ... and scanning, besides the usual windows, squares of this share of the shorter side
    # (`gst.detect.blazepose.zoomed_windows`; 0: none), where people too small for the usual
    # windows are larger (the lab's bystander at the back of cam02), `zoom_per_run` of them
    # per run in turn, all of them on the first run (`ZoomedScan`; at 544x960, 10 windows: all
    # of them every 4 runs, 40 processed frames)
    look_again_zoom: float = 2 / 3
    zoom_per_run: int = 3
    # a person found in a zoomed window only: limb landmarks in the frame, and their median
    # confidence at least this (the lab's people: 0.82-1.0; its anatomical skeleton model 0.57,
    # a camera mount 0.01-0.09, both cut by the frame's edge)
    zoom_min_confidence: float = 0.75
    # A tracked person whose mask box's thumbnail changed by at most this many grey levels (99th
    # percentile) since their landmarks were computed keeps those landmarks (0: always compute);
    # on the lab capture the bystander changes by 1-3.5 levels over 5 frames, the two people
    # who move by 5-60 in one frame
    still_change: float = 4.0
    still_refresh: int = 30  # ... but at most this many frames in a row
    # A tracked person the landmark model loses (presence below `min_presence`), or whose region
    # slid onto someone else's skeleton, has their last region looked at again for this many
    # processed frames (0: never): the detector finds people by the face, and one who walks
    # behind another with their head hidden is found only where they were (docs/
    # track_evaluation.md, "Lost behind someone")
    lost_retry: int = 10
    # ... with everyone kept painted out, their masks dilated by a square of these pixels (grown
    # by half of it on each side: 9 grows them by 4 px)
    lost_grow: int = 9
    # ... and kept where at most this share of their limb landmarks lies on the painted people:
    # one who stands behind another is seen beside them (a grey silhouette is person-shaped;
    # the lab's people found beside another: 8-33 %, silhouettes read as a person: 42-100 %)
    lost_max_covered: float = 0.34
    # A tracked person whose landmarks in their region continue their previous frame's (median
    # limb-joint distance at most this share of their size; `same_person`), whole in the frame
    # and sure of their limbs (`zoom_min_confidence`), stays tracked where the model doubts
    # them (presence below `min_presence`) and, followed behind someone, where more of their
    # limbs than `lost_max_covered` lie on the painted people. cam03's man, in plain view in his
    # fast turn, had presence 0.09-0.45 with his skeleton 0-2 % of his size from the frame
    # before's and limb visibility 0.92-0.95, and behind the woman 19-36 % of his limbs on her
    # (2-3 %, 0.72-0.84): lost in 11 of 100 frames (docs/track_evaluation.md, "Doubted but
    # continuing"). 0: never.
    continue_distance: float = 0.05
    batch: bool = True  # all regions of a frame in one landmark-model call
    threads: int = 1  # LiteRT threads per interpreter

    def __post_init__(self):
        if (
            self.detect_every < 1
            or self.max_side < 64
            or self.threads < 1
            or self.still_change < 0
            or self.still_refresh < 1
            or self.lost_retry < 0
            or self.continue_distance < 0
        ):
            raise ValueError(
                f"person model: detect_every >= 1, max_side >= 64, threads >= 1, still_change >= "
                f"0, still_refresh >= 1, lost_retry >= 0 and continue_distance >= 0 expected, got "
                f"{self.detect_every}, {self.max_side}, {self.threads}, {self.still_change}, "
                f"{self.still_refresh}, {self.lost_retry}, {self.continue_distance}"
            )
        if not 0 <= self.look_again_overlap <= 1:
            raise ValueError(
                f"person model: look_again_overlap must be in [0, 1], got {self.look_again_overlap}"
            )
        if (
            not 0 <= self.look_again_zoom < 1
            or self.zoom_per_run < 1
            or not 0 <= self.zoom_min_confidence <= 1
        ):
            raise ValueError(
                f"person model: look_again_zoom in [0, 1), zoom_per_run >= 1 and "
                f"zoom_min_confidence in [0, 1] expected, got {self.look_again_zoom}, "
                f"{self.zoom_per_run}, {self.zoom_min_confidence}"
            )
        if self.lost_grow < 0 or not 0 <= self.lost_max_covered <= 1:
            raise ValueError(
                f"person model: lost_grow >= 0 and lost_max_covered in [0, 1] expected, got "
                f"{self.lost_grow}, {self.lost_max_covered}"
            )
        if not 0 < self.min_presence < 1:
            raise ValueError(
                f"person model: min_presence must be in (0, 1), got {self.min_presence}"
            )

    def settings(self) -> dict:
        """What determines the detections (`threads` and `batch` do not: same numbers)."""
        d = asdict(self)
        d.pop("threads")
        d.pop("batch")
        return d


def _crop_mask(r: RegionLandmarks, skeleton_width: float) -> np.ndarray:
    """(S, S) bool: the person's mask in the region's crop, within `skeleton_width` x crop side
    of their skeleton (the model segments everyone in its region)."""
    lm_crop = r.crop_points(r.landmarks[:, :2])
    near = skeleton_support(lm_crop, r.mask_logits.shape, skeleton_width * LANDMARK_SIZE)
    return (r.mask_logits > 0) & near


def mask_box(r: RegionLandmarks, skeleton_width: float) -> np.ndarray | None:
    """Corner-convention box (x0, y0, x1, y1) in the region's image of the person's mask (the
    crop's segmentation within `skeleton_width` x crop side of their skeleton), or None."""
    ys, xs = np.nonzero(_crop_mask(r, skeleton_width))
    if len(xs) == 0:
        return None
    to_image = cv2.invertAffineTransform(r.to_crop)
    u = to_image[0, 0] * xs + to_image[0, 1] * ys + to_image[0, 2]
    v = to_image[1, 0] * xs + to_image[1, 1] * ys + to_image[1, 2]
    half = 0.5 * r.roi.side / LANDMARK_SIZE  # half a crop pixel, in image pixels
    # pixel centres at integers -> pixel-corner convention: + 0.5
    return np.array([u.min() - half, v.min() - half, u.max() + half, v.max() + half]) + 0.5


def paint_out_people(
    image: np.ndarray,
    people: list[RegionLandmarks],
    skeleton_width: float,
    grow: int,
    around: list[BodyRoi] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A copy of `image` with the people's masks (grown by `grow` pixels) filled with the
    image's mean colour, and that (H, W) bool cover: what stands behind them is left for the
    landmark model to see. With `around`, only the box that holds those regions is painted
    (all a landmark model looking there sees; far cheaper than the whole frame)."""
    h, w = image.shape[:2]
    x0, y0, x1, y1 = 0, 0, w, h
    if around:
        corners = np.concatenate([r.corners() for r in around])
        x0, y0 = np.clip(np.floor(corners.min(axis=0)).astype(int) - grow, 0, [w, h])
        x1, y1 = np.clip(np.ceil(corners.max(axis=0)).astype(int) + grow + 1, 0, [w, h])
    covered = np.zeros((h, w), bool)
    if x1 <= x0 or y1 <= y0:
        return image.copy(), covered
    window = np.zeros((y1 - y0, x1 - x0), np.uint8)
    for r in people:
        crop = _crop_mask(r, skeleton_width).astype(np.uint8)
        to_window = cv2.invertAffineTransform(r.to_crop) - [[0, 0, x0], [0, 0, y0]]
        window |= cv2.warpAffine(crop, to_window, window.shape[::-1], flags=cv2.INTER_NEAREST)
    if grow > 0:
        window = cv2.dilate(window, np.ones((grow, grow), np.uint8))
    covered[y0:y1, x0:x1] = window > 0
    return fill_where(image, covered, mean_colour(image)), covered


def share_covered(landmarks: np.ndarray, covered: np.ndarray) -> float:
    """The share of a person's limb landmarks (LIMB_JOINTS) that lie on `covered` pixels."""
    h, w = covered.shape
    uv = np.round(landmarks[LIMB_JOINTS, :2]).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return float(covered[uv[inside, 1], uv[inside, 0]].sum() / len(uv))


THUMB = 32  # side of the thumbnails that tell a still person from one who moved


def box_thumbnail(image: np.ndarray, box: np.ndarray, grow: float = 0.1) -> np.ndarray:
    """Grey (THUMB, THUMB) float32 thumbnail of the part of `image` inside the corner-convention
    `box` grown by `grow` of its size on every side (area-averaged, so that a compressed video's
    pixel noise averages out)."""
    h, w = image.shape[:2]
    gx, gy = grow * (box[2] - box[0]), grow * (box[3] - box[1])
    x0, y0 = max(0, int(box[0] - gx)), max(0, int(box[1] - gy))
    x1, y1 = min(w, int(np.ceil(box[2] + gx))), min(h, int(np.ceil(box[3] + gy)))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return np.zeros((THUMB, THUMB), np.float32)
    patch = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY)
    return cv2.resize(patch, (THUMB, THUMB), interpolation=cv2.INTER_AREA).astype(np.float32)


@dataclass(frozen=True)
class _Lost:
    """A lost person's last region (work pixels), the processed frames it is still looked at,
    and how many people were tracked before the loss: once as many are tracked again, the lost
    one has been found (by the detector, or in another region) and is no longer looked for."""

    roi: BodyRoi
    frames_left: int
    people: int


@dataclass
class _Seen:
    """A tracked person's last computed landmarks (result, mask box), the thumbnail of their mask
    box in the frame they were computed on, and the frames they have been kept since."""

    found: tuple
    thumbnail: np.ndarray
    kept_for: int = 0


def to_frame(
    landmarks: np.ndarray, box: np.ndarray, small_hw: tuple[int, int], frame_hw: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks (N, >=2) and a box (x0, y0, x1, y1) read on the resized frame (`small_hw`),
    in the full frame's pixels (pixel centres at integers in both; the box's corners clipped
    to the frame). Each axis by the resize's own ratio: rounding the resized size made it
    differ from the requested scale, up to a pixel's shift over 2704x1520 or 4096x2160."""
    (hs, ws), (h, w) = small_hw, frame_hw
    ratio = np.array([ws / w, hs / h])
    lm = np.asarray(landmarks).copy()
    lm[:, :2] = (lm[:, :2] + 0.5) / ratio - 0.5
    full = np.clip(np.asarray(box, np.float64) / np.tile(ratio, 2), 0, [w, h, w, h])
    return lm, full


class PersonModelDetector:
    """People in a stream of frames from one camera (keeps tracking state across frames)."""

    def __init__(
        self, config: PersonModelConfig | None = None, *, models_dir: str | Path | None = None
    ):
        self.config = config or PersonModelConfig()
        c = self.config
        self.model = BlazePose(models_dir, threads=c.threads)
        self.landmarker = BatchedLandmarks(models_dir, threads=c.threads)
        self._people: list[BodyRoi] = []  # next frame's regions, work pixels
        self._seen: list[_Seen | None] = []  # per region: the still-person check's state
        self._last: int | None = None
        self._since_detect = 0
        self.detector_runs = 0  # frames on which the person detector ran (for benchmarks)
        self.regions = 0  # landmark-model regions evaluated
        self.still_kept = 0  # regions whose landmarks were kept from an earlier frame
        self._zoom = ZoomedScan(c.look_again_zoom, c.zoom_per_run)
        self._probation: set[BodyRoi] = set()  # next regions of the second look's new finds
        self._lost: list[_Lost] = []  # lost people's last regions, looked at again
        self._behind: set[BodyRoi] = set()  # next regions of people found behind others
        self.found_again = 0  # people found again in their last region (for benchmarks)
        self._previous: list[np.ndarray] = []  # per region: the landmarks that gave it
        self.continued = 0  # doubted readings kept as continuing their person (for benchmarks)
        self._doubted: set[int] = set()  # this frame's continued readings (ids of the results)

    def reset(self) -> None:
        self._people, self._seen, self._last, self._since_detect = [], [], None, 0
        self._lost, self._behind, self._previous = [], set(), []
        self._zoom.reset()
        self._probation = set()

    def _still(self, image: np.ndarray, i: int) -> tuple | None:
        """The kept (result, box) of tracked person `i` if their mask box has not changed."""
        seen, c = self._seen[i], self.config
        if seen is None or c.still_change <= 0 or seen.kept_for >= c.still_refresh:
            return None
        change = np.abs(box_thumbnail(image, seen.found[1]) - seen.thumbnail)
        if float(np.percentile(change, 99)) > c.still_change:
            return None
        seen.kept_for += 1
        return seen.found

    def _follow(self, image: np.ndarray) -> list[tuple | None]:
        """Per tracked person: (result, box), or None where they are lost or followed behind
        others (`_behind`); the landmark model runs in one call for those who moved."""
        out = [self._still(image, i) for i in range(len(self._people))]
        todo = [i for i, o in enumerate(out) if o is None and self._people[i] not in self._behind]
        self.still_kept += sum(o is not None for o in out)
        results = self._landmarks(image, [self._people[i] for i in todo])
        for i, r in zip(todo, results, strict=True):
            accepted = self._accept([r], image.shape[0]) or self._continuing(
                r, self._previous[i], image.shape[:2]
            )
            # someone the second look found is confirmed only where their own region still
            # shows a whole person, sure of their limbs (the lab's skeleton model: 0.08-0.72)
            if accepted and self._people[i] in self._probation:
                ok = whole_and_sure(r.landmarks, image.shape[:2], self.config.zoom_min_confidence)
                accepted = accepted if ok else []
            out[i] = accepted[0] if accepted else None
        return out

    def _continuing(
        self, r: RegionLandmarks, previous: np.ndarray | None, shape: tuple[int, int]
    ) -> list[tuple]:
        """[(r, box)] where the doubted reading `r` continues its person's `previous` landmarks
        whole and sure (`continue_distance`), else []."""
        c = self.config
        if (
            previous is None
            or c.continue_distance <= 0
            or not same_person(r.landmarks, previous, c.continue_distance)
            or not whole_and_sure(r.landmarks, shape, c.zoom_min_confidence)
        ):
            return []
        accepted = self._accept([r], shape[0], min_presence=0.0)
        self.continued += len(accepted)
        self._doubted.update(id(a) for a, _ in accepted)
        return accepted

    def _look_behind(
        self,
        image: np.ndarray,
        kept: list[tuple],
        rois: list[BodyRoi],
        previous: list[np.ndarray | None],
    ) -> list:
        """The landmark model's accepted (result, box) or None in each of `rois`, with everyone
        `kept` painted out by their masks: where one person walked behind another, their region
        otherwise shows the one in front. A region whose person the model doubts while their
        limbs lie in the frame is looked at once more where it places them (`look_twice`): the
        region is the one they had when last seen (cam03's man behind the woman: presence
        0.15-0.59 in his stale regions, an even chance at `min_presence` 0.5). `previous`: per
        region, the landmarks of the frame before for people followed behind others (a
        reading that continues them stays, `_continuing`), None for the lost."""
        c = self.config
        painted, covered = paint_out_people(
            image, [r for r, _ in kept], c.skeleton_width, c.lost_grow, around=rois
        )
        results = look_twice(
            self._landmarks(painted, rois),
            lambda again: self._landmarks(painted, again),
            c.min_presence,
            image.shape[:2],
            0.0,
        )
        out = []
        for r, before in zip(results, previous, strict=True):
            accepted = self._accept([r], image.shape[0])
            if not accepted or share_covered(r.landmarks, covered) > c.lost_max_covered:
                accepted = self._continuing(r, before, image.shape[:2])
            out.append(accepted[0] if accepted else None)
        return out

    def _landmarks(self, image: np.ndarray, rois: list[BodyRoi]) -> list[RegionLandmarks]:
        self.regions += len(rois)
        if self.config.batch:
            return self.landmarker(image, rois)
        return [r for roi in rois for r in self.landmarker(image, [roi])]

    def _accept(
        self, results: list[RegionLandmarks], image_h: int, min_presence: float | None = None
    ) -> list[tuple]:
        """(result, box) of the regions holding a person (presence at least `min_presence`,
        default the config's) tall enough, in order."""
        c = self.config
        floor = c.min_presence if min_presence is None else min_presence
        out = []
        for r in results:
            if r.presence < floor:
                continue
            box = mask_box(r, c.skeleton_width)
            if box is None or box[3] - box[1] < c.min_height_frac * image_h:
                continue
            out.append((r, box))
        return out

    def _new_regions(
        self, image: np.ndarray, kept: list[tuple], windows: list | None = None
    ) -> list[BodyRoi]:
        """Regions of detector hits (in `windows`, default the usual ones) that are not a person
        already kept (same region)."""
        rois = []
        for d in self.model.detect(image, windows):
            roi = roi_from_alignment(d.keypoints[0], d.keypoints[1])
            if not any(same_region(roi, r.next_roi, self.config.same_region) for r, _ in kept):
                rois.append(roi)
        return rois

    def _look_again(self, image: np.ndarray, known: list[tuple]) -> list[tuple]:
        """(result, box) of the people the detector finds with the `known` ones painted out,
        beside them: where two overlap, the landmark model's loop cannot keep them apart, and
        waiting for the detector is safer. They must stand whole in the frame, and those found
        only in the zoomed windows must be sure of their limbs too
        (`gst.detect.persons.whole_and_sure`): things that look like a person up close or once
        the people are painted out (the lab's anatomical skeleton model, a camera mount) are
        found there too."""
        c = self.config
        boxes = [box for _, box in known]
        painted = paint_out(image, boxes)
        usual = self._new_regions(painted, known)
        windows = self._zoom.next(*image.shape[1::-1])
        zoomed = [
            roi
            for roi in (self._new_regions(painted, known, windows) if windows else [])
            if not any(same_region(roi, u, c.same_region) for u in usual)
        ]
        results = self._landmarks(image, usual + zoomed)
        # a zoomed hit's region whose person the landmark model does not see is looked at once
        # more where it places them (`look_twice`)
        results[len(usual) :] = look_twice(
            results[len(usual) :],
            lambda again: self._landmarks(image, again),
            c.min_presence,
            image.shape[:2],
            c.zoom_min_confidence,
        )
        from_zoom = {r.roi for r in results[len(usual) :]}
        found = self._accept(results, image.shape[0])
        # Everyone found here must stand whole in the frame, and those found in a zoomed window
        # only must be sure of their limbs too: with the people painted out, the lab's skeleton
        # model at the right edge reads as a person in the usual windows (presence 0.99, limb
        # landmarks up to 110 px beyond the frame's edge, median confidence 0.16)
        h_w = image.shape[:2]
        kept = [
            (r, box)
            for r, box in found
            if all(shared(box, b) <= c.look_again_overlap for b in boxes)
            and whole_and_sure(r.landmarks, h_w, c.zoom_min_confidence if r.roi in from_zoom else 0)
        ]
        self._probation |= {r.next_roi for r, _ in kept}
        return kept

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        c = self.config
        frame_bgr = as_bgr_frame(frame_bgr)  # grey frames crashed in painting out (2-D work image)
        if self._last is not None and not 0 < frame_index - self._last <= c.max_gap:
            self.reset()
        self._last = frame_index
        h, w = frame_bgr.shape[:2]
        s = min(1.0, c.max_side / max(h, w))
        small = (
            frame_bgr
            if s == 1.0
            # at least a pixel: a 1-pixel strip rounded to 0 across and failed in OpenCV
            else cv2.resize(
                frame_bgr,
                (max(1, round(w * s)), max(1, round(h * s))),
                interpolation=cv2.INTER_AREA,
            )
        )
        sh = small.shape[0]
        self._doubted.clear()
        followed = self._follow(small)
        behind = [i for i, roi in enumerate(self._people) if roi in self._behind]
        tracked = [f for f in followed if f is not None]
        # continued though the model doubted them (`_continuing`): the detector looks for a
        # surer reading of them, which replaces theirs (their region drifts on doubtful ones)
        doubted = [f for f in tracked if id(f[0]) in self._doubted]
        sure = [f for f in tracked if id(f[0]) not in self._doubted]
        lost = len(tracked) + len(behind) < len(self._people) or bool(doubted)
        if not self._people or lost or self._since_detect + 1 >= c.detect_every:
            self.detector_runs += 1
            self._since_detect = 0
            found = self._accept(self._landmarks(small, self._new_regions(small, sure)), sh)
            if c.look_again and (tracked or found):
                found += self._look_again(small, sure + found + doubted)
        else:
            self._since_detect += 1
            found = []
        # Tracked people first (they keep their place), then new ones, then the doubted, those
        # behind others and the lost ones found again where they were; a skeleton repeating a
        # kept one's is the same person seen from a second region.
        kept: list[tuple] = []
        repeats: set[int] = set()  # ids of the results dropped as a repeat

        def keep(candidates) -> None:
            for r, box in candidates:
                if any(
                    same_person(r.landmarks, k.landmarks, c.duplicate_distance) for k, _ in kept
                ):
                    repeats.add(id(r))
                else:
                    kept.append((r, box))

        keep(sure + found + doubted)
        # a lost person is looked for while fewer people are kept than before the loss
        self._lost = [m for m in self._lost if len(kept) + len(behind) < m.people]
        second = [self._people[i] for i in behind] + [m.roi for m in self._lost]
        before_then = [self._previous[i] for i in behind] + [None] * len(self._lost)
        looked = self._look_behind(small, kept, second, before_then) if second else []
        for i, f in zip(behind, looked, strict=False):
            followed[i] = f
        again = [(k, f) for k, f in enumerate(looked[len(behind) :]) if f is not None]
        before = len(kept)
        keep([f for f in looked if f is not None])
        kept_ids = {id(r) for r, _ in kept[before:]}
        hits = {k for k, f in again if id(f[0]) in kept_ids}
        self.found_again += len(hits)
        # who is looked for again: the tracked people lost in this frame (not those the second
        # look found and their own region did not confirm), and those whose region slid onto
        # someone else's skeleton (dropped as a repeat)
        gone = [
            roi
            for f, roi in zip(followed, self._people, strict=True)
            if (f is None and roi not in self._probation) or (f and id(f[0]) in repeats)
        ]
        self._lost = [
            replace(m, frames_left=m.frames_left - 1)
            for k, m in enumerate(self._lost)
            if k not in hits and m.frames_left > 1
        ] + [_Lost(roi, c.lost_retry, len(self._people)) for roi in gone if c.lost_retry > 0]
        self._people = [r.next_roi for r, _ in kept]
        self._previous = [r.landmarks for r, _ in kept]
        # followed on the painted frame while their box still overlaps someone's
        self._behind = {
            r.next_roi
            for k, (r, box) in enumerate(kept)
            if k >= before and any(shared(box, b) > 0 for j, (_, b) in enumerate(kept) if j != k)
        }
        self._probation &= set(self._people)  # confirmed or dropped: off probation
        # The still-person state: kept from the earlier frame, or fresh where the landmarks were
        # just computed in the region their own landmarks gave. A detector's find is not kept
        # before that has confirmed it: a still object the detector mistakes for a person once
        # (cam02's anatomical skeleton) would otherwise stay for `still_refresh` frames.
        earlier = {
            id(f[0]): seen
            for f, seen in zip(followed, self._seen, strict=True)
            if seen is not None and f is seen.found
        }
        # a doubted reading is no still person's: kept as one, it came back as sure the next
        # frame and the detector stopped looking for a surer reading of them
        confirmed = {id(r) for r, _ in tracked if id(r) not in self._doubted}
        self._seen = [
            earlier.get(id(r))
            or (_Seen((r, box), box_thumbnail(small, box)) if id(r) in confirmed else None)
            for r, box in kept
        ]
        out = []
        for r, box in kept:
            lm, full = to_frame(r.landmarks, box, small.shape[:2], (h, w))
            if full[2] <= full[0] or full[3] <= full[1]:
                continue
            out.append(Detection(box=full, score=r.presence, landmarks=lm))
        return out
