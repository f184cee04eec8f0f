"""BlazePose on CPU through LiteRT: person detection, 33 landmarks and a segmentation mask
per person.

Two TFLite models (see `gst.detect.weights`) run in the `ai-edge-litert` interpreter:

- the detector takes the frame letterboxed to 224x224 RGB in [-1, 1] and scores 2254 SSD
  anchors. Each anchor regresses a box and 4 keypoints: hip centre, a point on the full-body
  circle, shoulder centre, a point on the upper-body circle. Scores go through a sigmoid (logits
  clipped to +-100); overlapping detections are merged by score-weighted averaging
  (MediaPipe's "weighted NMS", IoU 0.3).
- the landmark model takes a rotated square region of interest, 256x256 RGB in [0, 1], and
  returns 39 landmarks (33 body + alignment points), a presence score, and 256x256
  segmentation logits of that person; the landmarks are refined from its 64x64 per-landmark
  heatmaps as MediaPipe's pose graph does (`refine_from_heatmaps`).

A region of interest comes from the hip centre and the full-body point: centre at the hips,
side 2.5 x their distance, rotated so that the body axis points up. It can also come from a
box (e.g. a background-subtraction blob), or from the previous frame's landmarks (tracking).
Portrait or landscape frames are also scanned in overlapping square tiles, so that people who
are small in the full letterboxed frame are still found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gst.detect.boxes import box_iou
from gst.detect.weights import model_paths

DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
N_BODY_LANDMARKS = 33
ROI_SCALE = 1.25  # the region is 1.25 x the body circle's diameter (MediaPipe's setting)


# --- detector: anchors and decoding ------------------------------------------------------------


def ssd_anchors() -> np.ndarray:
    """(2254, 2) anchor centres in [0, 1] of BlazePose's detector.

    Five SSD layers with strides 8, 16, 32, 32, 32 over a 224 input; layers with the same
    stride share one grid, and each layer adds 2 anchors per cell (aspect 1 and the
    interpolated scale). With fixed anchor size all anchors of a cell are the same point, so
    the layout is 28x28x2, 14x14x2 and 7x7x6, cells in row-major order.
    """
    centres = []
    for stride, per_cell in ((8, 2), (16, 2), (32, 6)):
        n = math.ceil(DETECTOR_SIZE / stride)
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        cell = np.stack([xs.ravel(), ys.ravel()], axis=1)
        centres.append(np.repeat(cell, per_cell, axis=0))
    return np.concatenate(centres).astype(np.float32)


_ANCHORS = ssd_anchors()


@dataclass(frozen=True)
class PoseDetection:
    """One detected person in image pixels."""

    score: float
    box: np.ndarray  # (4,) x0, y0, x1, y1 of the detector's box (face and upper body)
    keypoints: (
        np.ndarray
    )  # (4, 2): hip centre, full-body circle point, shoulder centre, upper-body point


def decode_detections(
    regressors: np.ndarray, logits: np.ndarray, min_score: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw detector outputs (2254, 12) and (2254,) -> scores (n,), boxes (n, 4), keypoints (n, 4, 2)
    in [0, 1] coordinates of the detector input, for the anchors scoring at least `min_score`."""
    if regressors.shape != (len(_ANCHORS), 12) or logits.shape != (len(_ANCHORS),):
        raise ValueError(
            f"detector outputs must be ({len(_ANCHORS)}, 12) and ({len(_ANCHORS)},), "
            f"got {regressors.shape} and {logits.shape}"
        )
    scores = 1.0 / (1.0 + np.exp(-np.clip(logits.astype(np.float64), -100.0, 100.0)))
    keep = scores >= min_score
    reg, anchors = regressors[keep] / DETECTOR_SIZE, _ANCHORS[keep]
    centre = reg[:, :2] + anchors
    half = reg[:, 2:4] / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    keypoints = reg[:, 4:12].reshape(-1, 4, 2) + anchors[:, None, :]
    return scores[keep], boxes, keypoints


def weighted_nms(
    scores: np.ndarray, boxes: np.ndarray, keypoints: np.ndarray, iou: float = 0.3
) -> list[PoseDetection]:
    """Merge detections that overlap by more than `iou`: the best score is kept, and its box and
    keypoints become the score-weighted mean of its group (steadier than keeping one anchor)."""
    order = np.argsort(-scores, kind="stable")
    free = np.ones(len(scores), dtype=bool)
    out = []
    for i in order:
        if not free[i]:
            continue
        group = free & (box_iou(boxes[i], boxes)[0] > iou)
        group[i] = True
        free &= ~group
        w = scores[group] / scores[group].sum()
        out.append(
            PoseDetection(
                float(scores[i]),
                (boxes[group] * w[:, None]).sum(0),
                (keypoints[group] * w[:, None, None]).sum(0),
            )
        )
    return out


def square_windows(width: int, height: int) -> list[tuple[int, int, int]]:
    """(x0, y0, side) of the squares scanned: the whole frame letterboxed, plus overlapping
    squares along the longer side when the frame is not square (none for a square frame)."""
    side = max(width, height)
    wins = [((width - side) // 2, (height - side) // 2, side)]
    short, long_ = min(width, height), max(width, height)
    if long_ > 1.2 * short:
        n = max(2, math.ceil((long_ - short) / (0.75 * short)) + 1)
        for k in range(n):
            off = round(k * (long_ - short) / (n - 1))
            wins.append((off, 0, short) if width > height else (0, off, short))
    return wins


def zoomed_windows(width: int, height: int, fraction: float) -> list[tuple[int, int, int]]:
    """(x0, y0, side) of squares `fraction` of the shorter side, overlapping by half along both
    axes and reaching every edge: a person too small for `square_windows` (a bystander at the
    back of a lab) is larger in them."""
    side = max(1, round(fraction * min(width, height)))

    def starts(extent: int) -> list[int]:
        if extent <= side:
            return [0]
        n = math.ceil((extent - side) / (side / 2)) + 1
        return [round(k * (extent - side) / (n - 1)) for k in range(n)]

    return [(x0, y0, side) for y0 in starts(height) for x0 in starts(width)]


class ZoomedScan:
    """Zoomed windows handed out a few per detector run, in turn over the frame, and all of
    them on the first run after `reset` (whoever stands at the back from the start is found at
    once; later arrivals within a sweep)."""

    def __init__(self, fraction: float, per_run: int):
        self.fraction, self.per_run = fraction, per_run
        self.reset()

    def reset(self) -> None:
        self._next, self._started = 0, False

    def next(self, width: int, height: int) -> list[tuple[int, int, int]]:
        """The windows of this run ([] when `fraction` is 0)."""
        if self.fraction <= 0:
            return []
        every = zoomed_windows(width, height, self.fraction)
        if not self._started:
            self._started = True
            return every
        take = [every[(self._next + k) % len(every)] for k in range(min(self.per_run, len(every)))]
        self._next = (self._next + len(take)) % len(every)
        return take


# --- regions of interest ---------------------------------------------------------------------


@dataclass(frozen=True)
class BodyRoi:
    """A rotated square around one person, in image pixels."""

    centre: tuple[float, float]
    side: float
    angle: float  # radians; the region's "up" is the image's up rotated by this angle

    def corners(self) -> np.ndarray:
        """(4, 2) image points of the crop's top-left, top-right, bottom-left and bottom-right
        corners."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        (cx, cy), side = self.centre, self.side
        x, y = np.array([-0.5, 0.5, -0.5, 0.5]) * side, np.array([-0.5, -0.5, 0.5, 0.5]) * side
        return np.c_[cx + x * c - y * s, cy + x * s + y * c]  # this order: to_crop's numbers

    def to_crop(self, size: int) -> np.ndarray:
        """2x3 affine matrix from image pixels to the size x size crop."""
        src = self.corners()[:3].astype(np.float32)
        dst = np.float32([[0, 0], [size, 0], [0, size]])
        return cv2.getAffineTransform(src, dst)


def roi_from_alignment(centre: np.ndarray, scale_point: np.ndarray) -> BodyRoi:
    """Region from the hip centre and the full-body circle point (detector keypoints 0 and 1, or
    landmarks 33 and 34): side ROI_SCALE x the circle's diameter, body axis turned upright."""
    d = np.asarray(scale_point, np.float64) - np.asarray(centre, np.float64)
    radius = float(np.hypot(*d))
    # The target angle is 90 degrees: the centre -> scale-point vector should point up.
    angle = math.pi / 2 - math.atan2(-d[1], d[0])
    angle = (angle + math.pi) % (2 * math.pi) - math.pi
    return BodyRoi((float(centre[0]), float(centre[1])), 2 * radius * ROI_SCALE, angle)


def roi_from_box(box: tuple[float, float, float, float]) -> BodyRoi:
    """Upright region around an x, y, w, h person box (a whole body): side 1.25 x its longer
    side."""
    x, y, w, h = box
    return BodyRoi((x + w / 2, y + h / 2), ROI_SCALE * max(w, h), 0.0)


def same_region(a: BodyRoi, b: BodyRoi, tolerance: float) -> bool:
    """Whether two regions frame the same body: centres within `tolerance` x the larger side
    and sides within that share of each other."""
    side = max(a.side, b.side)
    d = np.hypot(a.centre[0] - b.centre[0], a.centre[1] - b.centre[1])
    return d < tolerance * side and abs(a.side - b.side) < tolerance * side


# --- landmarks refined from the heatmaps -----------------------------------------------------


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-np.clip(x.astype(np.float64), -30, 30)))).astype(np.float32)


HEATMAP_KERNEL = 7  # MediaPipe's pose graph: RefineLandmarksFromHeatmapCalculator's kernel_size
HEATMAP_MIN_CONFIDENCE = 0.5  # ... and its min_confidence_to_refine
HEATMAPS = (64, 64, 39)  # the landmark model's heatmap output (per-landmark logits)


def refine_from_heatmaps(
    raw: np.ndarray,
    heatmaps: np.ndarray,
    kernel: int = HEATMAP_KERNEL,
    min_confidence: float = HEATMAP_MIN_CONFIDENCE,
) -> np.ndarray:
    """Landmarks moved to their heatmap's local centre of mass, as MediaPipe's pose graph does.

    `raw` (n, P, >=2) holds the landmark model's regressed x, y in crop pixels (of
    LANDMARK_SIZE); `heatmaps` (n, H, W, P) its per-landmark logits. For each landmark the
    kernel x kernel cells around its (truncated) cell are weighted by their sigmoid; where the
    largest weight reaches `min_confidence`, x, y become the weighted mean cell index over the
    heatmap's size (MediaPipe's formula: cell indices, no half-cell shift). Cells outside the
    heatmap weigh nothing. A landmark regressed outside the crop keeps its place (MediaPipe
    would pull one within the kernel of the edge onto the edge cells; a limb cut off by the
    crop is better left where the regression put it, and that is what was measured).
    Returns a copy of `raw` with x, y replaced. On the demo, with the virtual markers fitted
    again on refined detections, the fused bodies went from 27.7 / 24.4 to 24.7 / 23.8 mm
    (docs/person_models.md, last section)."""
    raw = np.asarray(raw)
    n, p = raw.shape[:2]
    hh, hw = heatmaps.shape[1:3]
    if heatmaps.shape != (n, hh, hw, p):
        raise ValueError(f"heatmaps of shape {heatmaps.shape} for landmarks {raw.shape}")
    off = (kernel - 1) // 2
    with np.errstate(invalid="ignore"):
        col = np.trunc(np.nan_to_num(raw[..., 0] / LANDMARK_SIZE * hw, nan=-1.0))
        row = np.trunc(np.nan_to_num(raw[..., 1] / LANDMARK_SIZE * hh, nan=-1.0))
    inside = (col >= 0) & (col < hw) & (row >= 0) & (row < hh)
    steps = np.arange(-off, off + 1)
    # (n, P, k) heatmap rows and columns of each window (only an inside centre's is used)
    rows = np.clip(row, 0, hh - 1).astype(np.int64)[..., None] + steps
    cols = np.clip(col, 0, hw - 1).astype(np.int64)[..., None] + steps
    in_heatmap = ((rows >= 0) & (rows < hh))[..., :, None] & ((cols >= 0) & (cols < hw))[
        ..., None, :
    ]
    ni = np.arange(n)[:, None, None, None]
    pi = np.arange(p)[None, :, None, None]
    logits = heatmaps[
        ni, np.clip(rows, 0, hh - 1)[..., :, None], np.clip(cols, 0, hw - 1)[..., None, :], pi
    ]
    weight = np.where(in_heatmap, _sigmoid(logits), 0.0)  # (n, P, k, k); outside: nothing
    total = weight.sum(axis=(2, 3))
    use = inside & (weight.max(axis=(2, 3)) >= min_confidence) & (total > 0)
    safe = np.where(total > 0, total, 1.0)
    mean_col = (weight.sum(axis=2) * cols).sum(axis=2) / safe
    mean_row = (weight.sum(axis=3) * rows).sum(axis=2) / safe
    out = raw.copy()
    out[..., 0] = np.where(use, mean_col / hw * LANDMARK_SIZE, raw[..., 0])
    out[..., 1] = np.where(use, mean_row / hh * LANDMARK_SIZE, raw[..., 1])
    return out


# --- the models ------------------------------------------------------------------------------


def import_litert():
    """LiteRT's Interpreter class, or an ImportError that says how to install it."""
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError as exc:  # the optional extra is not installed
        raise ImportError(
            "the BlazePose person models need the LiteRT interpreter: "
            'pip install -e ".[detect]" (package ai-edge-litert)'
        ) from exc
    return Interpreter


class _Model:
    """A LiteRT interpreter with its tensor indices read once: `get_input_details` and
    `get_output_details` build fresh dicts on every call, a measurable share of the tracking
    loop's person-model thread when asked for every frame."""

    def __init__(self, path: Path, threads: int, batch: int = 1, size: int | None = None):
        self.interpreter = it = import_litert()(model_path=str(path), num_threads=threads)
        self.input = it.get_input_details()[0]["index"]
        if batch != 1:
            it.resize_tensor_input(self.input, [batch, size, size, 3])
        it.allocate_tensors()
        # outputs keyed by their shape without the batch dimension (each one's is unique)
        self.outputs = [
            (tuple(int(v) for v in d["shape"][1:]), d["index"]) for d in it.get_output_details()
        ]

    def __call__(self, x: np.ndarray) -> dict[tuple[int, ...], np.ndarray]:
        it = self.interpreter
        it.set_tensor(self.input, x)
        it.invoke()
        return {shape: it.get_tensor(index) for shape, index in self.outputs}


@dataclass(frozen=True)
class PersonSegment:
    """The landmark model's answer for one region, mapped back to the image."""

    presence: float  # probability that a person is in the region
    probability: np.ndarray  # (H, W) float32 person probability in the image (0 outside the region)
    landmarks: np.ndarray  # (33, 3) x, y in image pixels and visibility in [0, 1]
    next_roi: BodyRoi  # where this person is expected in the next frame
    # (33, 3) float32 metres, origin at the mid-hips, axes of the region of interest (x right,
    # y down, z away from the camera, as in the crop; rotated with the ROI's angle): the model's
    # (1, 117) output = 39 x 3, first 33 (docs/landmark_prior.md measures their accuracy).
    world_landmarks: np.ndarray | None = None


def as_bgr_frame(image: np.ndarray) -> np.ndarray:
    """`image` as an (H, W, 3) uint8 BGR frame: grey and BGRA frames converted; other dtypes
    refused (a uint16 frame gave no detection and a landmark reading 42 px off, at presence
    0.997, which later stages could not tell from a real one)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(
            f"frames must be uint8 (0-255) images, got {image.dtype}; convert them first "
            "(16-bit: image >> 8)"
        )
    if image.size == 0 and image.ndim in (2, 3):  # OpenCV's assertion said nothing of the frame
        raise ValueError(f"empty frame of shape {image.shape}: expected H, W >= 1")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"frames must be (H, W) grey or (H, W, 3) BGR, got shape {image.shape}")
    return image


class BlazePose:
    """Person detector plus landmark/segmentation model. Not thread-safe: one per worker."""

    def __init__(
        self,
        models_dir: str | Path | None = None,
        threads: int = 1,
        min_score: float = 0.5,
        refine_heatmaps: bool = True,
    ):
        paths = model_paths(models_dir)
        self.detector = _Model(paths["detector"], threads)
        self.landmarker = _Model(paths["landmarks"], threads)
        self.min_score = min_score
        # landmarks refined from the heatmaps (`refine_from_heatmaps`)
        self.refine_heatmaps = refine_heatmaps

    def detect(
        self, image: np.ndarray, windows: list[tuple[int, int, int]] | None = None
    ) -> list[PoseDetection]:
        """People in a BGR image: every scan window ((x0, y0, side) squares; default
        `square_windows`), merged by weighted NMS, in image pixels."""
        image = as_bgr_frame(image)
        h, w = image.shape[:2]
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        scores, boxes, kps = [], [], []
        for x0, y0, side in square_windows(w, h) if windows is None else windows:
            # Cut the window out of a zero-padded frame (the full-frame window is a letterbox).
            m = np.float32(
                [
                    [DETECTOR_SIZE / side, 0, -x0 * DETECTOR_SIZE / side],
                    [0, DETECTOR_SIZE / side, -y0 * DETECTOR_SIZE / side],
                ]
            )
            # (warpAffine has no area filter: INTER_AREA would silently be bilinear too.)
            win = cv2.warpAffine(
                rgb,
                m,
                (DETECTOR_SIZE, DETECTOR_SIZE),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
            )
            out = self.detector((win.astype(np.float32) / 127.5 - 1.0)[None])
            s, b, k = decode_detections(
                out[(len(_ANCHORS), 12)][0], out[(len(_ANCHORS), 1)][0, :, 0], self.min_score
            )
            offset = np.array([x0, y0], np.float32)
            scores.append(s)
            boxes.append(b * side + np.tile(offset, 2))
            kps.append(k * side + offset)
        if not scores:  # no windows
            return []
        return weighted_nms(np.concatenate(scores), np.concatenate(boxes), np.concatenate(kps))

    def segment(self, image: np.ndarray, roi: BodyRoi) -> PersonSegment:
        """Landmarks and segmentation of the person in `roi` of a BGR image."""
        image = as_bgr_frame(image)
        h, w = image.shape[:2]
        to_crop = roi.to_crop(LANDMARK_SIZE)
        crop = cv2.warpAffine(
            image,
            to_crop,
            (LANDMARK_SIZE, LANDMARK_SIZE),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
        )
        rgb = cv2.cvtColor(crop, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        out = self.landmarker(rgb[None])
        raw = out[(195,)][0].reshape(39, 5)
        if self.refine_heatmaps:
            raw = refine_from_heatmaps(raw[None], out[HEATMAPS])[0]
        presence = float(np.clip(out[(1,)][0, 0], 0.0, 1.0))
        logits = out[(LANDMARK_SIZE, LANDMARK_SIZE, 1)][0, :, :, 0]
        prob_crop = (1.0 / (1.0 + np.exp(-np.clip(logits, -30, 30)))).astype(np.float32)
        to_image = cv2.invertAffineTransform(to_crop)
        prob = cv2.warpAffine(
            prob_crop, to_image, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        xy = np.c_[raw[:, :2], np.ones(39)] @ to_image.T
        visibility = 1.0 / (1.0 + np.exp(-np.clip(raw[:N_BODY_LANDMARKS, 3], -30, 30)))
        landmarks = np.c_[xy[:N_BODY_LANDMARKS], visibility].astype(np.float32)
        world = out[(117,)][0].reshape(39, 3)[:N_BODY_LANDMARKS].astype(np.float32)
        return PersonSegment(
            presence, prob, landmarks, roi_from_alignment(xy[33], xy[34]), world.copy()
        )


# --- batched landmarks in the region's own crop (tracking) ---------------------------------------


@dataclass(frozen=True)
class RegionLandmarks:
    """The landmark model's answer for one region, kept in the region's crop: no full-frame
    warp of the segmentation (what tracking needs is the landmarks and the mask's extent)."""

    roi: BodyRoi
    presence: float  # probability that a person is in the region
    landmarks: np.ndarray  # (33, 3) float32: x, y in image pixels, confidence in [0, 1]
    visibility: np.ndarray  # (33,) float32 landmark visibility
    landmark_presence: np.ndarray  # (33,) float32 landmark presence (in the frame, not cut off)
    world_landmarks: np.ndarray  # (33, 3) float32 metres, hip-centred, the region's axes
    mask_logits: np.ndarray  # (S, S) float32 segmentation logits in the crop (S = LANDMARK_SIZE)
    to_crop: np.ndarray  # (2, 3) affine: image pixels -> crop pixels
    next_roi: BodyRoi  # where this person is expected in the next frame

    def crop_points(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) image pixels -> crop pixels."""
        return np.c_[xy, np.ones(len(xy))] @ self.to_crop.T


class BatchedLandmarks:
    """The landmark model over several regions of one image in one interpreter call.

    The model accepts a batch dimension (LiteRT's `resize_tensor_input`); its answers are the
    same numbers as one call per region. Each person's `confidence` is the project's convention,
    landmark visibility x landmark presence. Not thread-safe: one per worker."""

    # Interpreters are kept for these batch sizes only, and a call of n regions runs as a few
    # of them (5 = 4 + 1; 19 = 8 + 8 + 2 + 1): re-allocating one for every change of the number
    # of regions costs more than the memory, but one per size seen grew without bound (an
    # interpreter for batch n holds n crops' working memory: sizes 1-8 took 624 MiB).
    BATCH_SIZES = (8, 4, 2, 1)

    def __init__(
        self, models_dir: str | Path | None = None, threads: int = 1, refine_heatmaps: bool = True
    ):
        self._path, self._threads = model_paths(models_dir)["landmarks"], threads
        # landmarks refined from the heatmaps (`refine_from_heatmaps`)
        self.refine_heatmaps = refine_heatmaps
        self._by_batch: dict[int, object] = {}

    def _for_batch(self, n: int) -> _Model:
        model = self._by_batch.get(n)
        if model is None:
            model = _Model(self._path, self._threads, batch=n, size=LANDMARK_SIZE)
            self._by_batch[n] = model
        return model

    def _run(self, rgb: np.ndarray) -> dict[tuple[int, ...], np.ndarray]:
        """The model on a batch of any size, as calls of the kept sizes (same numbers: the
        model's answer for a region does not depend on the others in its batch)."""
        parts, start = [], 0
        while start < len(rgb):
            size = next(b for b in self.BATCH_SIZES if b <= len(rgb) - start)
            parts.append(self._for_batch(size)(rgb[start : start + size]))
            start += size
        if len(parts) == 1:
            return parts[0]
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}

    def __call__(self, image: np.ndarray, rois: list[BodyRoi]) -> list[RegionLandmarks]:
        """Landmarks of the person in each region of a BGR image (one call for all regions)."""
        if not rois:
            return []
        image = as_bgr_frame(image)
        mats = [roi.to_crop(LANDMARK_SIZE) for roi in rois]
        crops = np.stack(
            [
                cv2.warpAffine(
                    image,
                    m,
                    (LANDMARK_SIZE, LANDMARK_SIZE),
                    flags=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT,
                )
                for m in mats
            ]
        )
        rgb = crops[..., ::-1].astype(np.float32) * np.float32(1 / 255)
        n = len(rois)
        out = self._run(rgb)
        raw = out[(195,)].reshape(n, 39, 5)
        if self.refine_heatmaps:
            raw = refine_from_heatmaps(raw, out[HEATMAPS])
        presence = np.clip(out[(1,)][:, 0], 0.0, 1.0)
        logits = out[(LANDMARK_SIZE, LANDMARK_SIZE, 1)][..., 0]
        world = out[(117,)].reshape(n, 39, 3)[:, :N_BODY_LANDMARKS]
        results = []
        for k, (roi, m) in enumerate(zip(rois, mats, strict=True)):
            to_image = cv2.invertAffineTransform(m)
            xy = np.c_[raw[k, :, :2], np.ones(39)] @ to_image.T
            vis = _sigmoid(raw[k, :N_BODY_LANDMARKS, 3])
            pres = _sigmoid(raw[k, :N_BODY_LANDMARKS, 4])
            results.append(
                RegionLandmarks(
                    roi,
                    float(presence[k]),
                    np.c_[xy[:N_BODY_LANDMARKS], vis * pres].astype(np.float32),
                    vis,
                    pres,
                    world[k].astype(np.float32, copy=True),
                    logits[k].astype(np.float32, copy=True),
                    m,
                    roi_from_alignment(xy[33], xy[34]),
                )
            )
        return results
