"""BlazePose's landmarks on crops that already frame one person (the extraction's, training's
and tracking's square crops): the whole crop is the landmark model's region of interest.

With `refine=True` (what the fusion uses), the model also runs as it was trained: the first
pass's alignment keypoints (hip centre, full-body scale point) give a region centred on the
hips, rotated upright, 1.25 x the body circle; the second pass runs there and on the same region
mirrored (left and right exchanged back), and the two are averaged. On tuning worlds this lowers
the median landmark error by 8-10 % (docs/fuse.md). With `masks`, pixels outside each crop's
person mask are dimmed first (`suppress_others`), so the model does not lock onto someone
overlapping the person.

The one place the crop pipelines run the landmark model; training, fusion and the lifting
dataset call it, and read the store's `landmarks` instead when the extraction wrote them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gst.detect.blazepose import LANDMARK_SIZE, N_BODY_LANDMARKS, BlazePose, BodyRoi


@dataclass(frozen=True)
class CropLandmarks:
    """BlazePose on N crops: crop-pixel landmarks with visibility, world landmarks (metres,
    mid-hip origin, the crop camera's axes; `PersonSegment.world_landmarks`) and presence.
    With `refine=True` the world landmarks are the second pass's, in the axes of its region,
    which is turned by that region's angle in the image plane (about 10 degrees on a lab crop):
    turn them back by it before comparing them with the crop camera's axes."""

    landmarks: np.ndarray  # (N, 33, 3) u, v in crop pixels, visibility in [0, 1]
    world: np.ndarray  # (N, 33, 3)
    presence: np.ndarray  # (N,)

    def __len__(self) -> int:
        return len(self.presence)

    def with_confidence(self) -> np.ndarray:
        """(N, 33, 3) u, v and confidence = visibility x the crop's presence (the crop store keeps
        visibility alone)."""
        out = self.landmarks.copy()
        out[..., 2] *= self.presence[:, None]
        return out


def _mirror_index() -> np.ndarray:
    from gst.body.markers import BLAZEPOSE_MIRROR  # imported late: gst.body loads torch

    return BLAZEPOSE_MIRROR


def suppress_others(image: np.ndarray, mask: np.ndarray, dim: float = 0.25) -> np.ndarray:
    """The crop with everything outside the person's mask (dilated by 4 % of the crop) dimmed to
    `dim` of its brightness."""
    import cv2

    k = max(3, int(0.04 * image.shape[0]) | 1)
    thr = 127 if mask.dtype == np.uint8 else 0.5
    keep = cv2.dilate((mask > thr).astype(np.uint8), np.ones((k, k), np.uint8))
    if not keep.any():
        return image
    scale = dim + (1.0 - dim) * keep[..., None].astype(np.float32)
    return (image.astype(np.float32) * scale).astype(np.uint8)


def _refined(model: BlazePose, image: np.ndarray, first) -> tuple:
    """Second pass on the first pass's alignment region, averaged with its mirror image."""
    roi = first.next_roi
    a = model.segment(image, roi)
    w = image.shape[1]
    mirrored = BodyRoi((w - 1 - roi.centre[0], roi.centre[1]), roi.side, -roi.angle)
    b = model.segment(np.ascontiguousarray(image[:, ::-1]), mirrored)
    flip = _mirror_index()
    lb = b.landmarks[flip].copy()
    lb[:, 0] = w - 1 - lb[:, 0]
    lms = np.c_[(a.landmarks[:, :2] + lb[:, :2]) / 2, (a.landmarks[:, 2] + lb[:, 2]) / 2]
    presence = (a.presence + b.presence) / 2
    # confidence = mean over the two passes of visibility x presence, as the store keeps it
    vis = (a.landmarks[:, 2] * a.presence + lb[:, 2] * b.presence) / 2 / max(presence, 1e-9)
    lms[:, 2] = vis
    return lms, a.world_landmarks, presence


def detect_crop_landmarks(
    images: np.ndarray,
    model: BlazePose | None = None,
    *,
    rgb: bool,
    progress=None,
    refine: bool = False,
    masks: np.ndarray | None = None,
) -> CropLandmarks:
    """The landmark model on (N, S, S, 3) uint8 crops (`rgb` says the channel order: CropSet
    images are RGB, store and video frames BGR), each crop as one upright region; `refine`: the
    second pass on the alignment region (module docstring); `masks` (N, S, S): the person's
    mask per crop, other pixels dimmed first. World landmarks are the (unmirrored) last pass's."""
    images = np.asarray(images)
    if images.size and images.dtype != np.uint8:  # read as 0-255 values: wrong, not refused
        raise ValueError(f"crops must be uint8 (0-255) images, got {images.dtype}")
    if images.size == 0:  # no crops: no landmarks
        images = np.zeros((0, 1, 1, 3), np.uint8)
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[1] != images.shape[2]:
        raise ValueError(
            f"crops must be (N, S, S, 3) square colour images, got shape {images.shape} "
            "(grey or RGBA crops read a channel as colour)"
        )
    n, size = len(images), images.shape[1]
    # one (S, S) mask per crop: fewer, or another size, failed mid-run with numpy's message
    if masks is not None and np.shape(masks) != (n, size, size):
        raise ValueError(
            f"masks must be ({n}, {size}, {size}), one per crop, got shape {np.shape(masks)}"
        )
    model = model or BlazePose(threads=1)
    roi = whole_crop_roi(size)
    lms = np.zeros((n, N_BODY_LANDMARKS, 3), np.float32)
    world = np.zeros((n, N_BODY_LANDMARKS, 3), np.float32)
    presence = np.zeros(n, np.float32)
    rows = (
        range(n)
        if progress is None
        else progress(range(n), description="BlazePose landmarks in crops", total=n)
    )
    for i in rows:
        img = images[i][..., ::-1] if rgb else images[i]
        if masks is not None:
            img = suppress_others(img, masks[i])
        img = np.ascontiguousarray(img)
        seg = model.segment(img, roi)
        if refine:
            lms[i], world[i], presence[i] = _refined(model, img, seg)
        else:
            lms[i], world[i], presence[i] = seg.landmarks, seg.world_landmarks, seg.presence
    return CropLandmarks(lms, world, presence)


def whole_crop_roi(size: int) -> BodyRoi:
    """The region that hands the landmark model a `size` px crop as it is. `BodyRoi.to_crop`
    maps the region's corners to the model input's edges (0 and 256) while `cv2.warpAffine`
    samples at pixel centres: the region centred at ((size - 1) / 2, ...) sampled every pixel
    half a pixel up and left of itself, a blur with a half-dark first row and column that moved
    its landmarks by a median 1.1 px (5-23 px on four of 20 lab crops). This centre samples
    pixel centres onto pixel centres (exactly the crop at 256 px). The answer is read back as
    on frames, half a model pixel (0.5 x size / 256) right of and below the feature, as before
    (docs/person_models.md, "Landmarks half a crop pixel off": measured, not corrected), so
    crop and frame readings stay alike."""
    centre = size / 2 + 0.5 * size / LANDMARK_SIZE - 0.5
    return BodyRoi((centre, centre), float(size), 0.0)
