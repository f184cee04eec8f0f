"""A person detector for static cameras, built on the extraction library's background model.

The background is learnt once per video from frames sampled across it (or from a clip of the
empty scene, which is what makes people who barely move visible); each frame's foreground is
cleaned (morphology, hole filling, component filters). A moving body often falls apart into
pieces (a limb against a wall of its own colour), so blobs stacked on top of each other are
grouped into one person box (`group_boxes`). With a calibrated camera each box is read as a
person standing on the floor (`gst.data.ground.ground_seed`) and dropped when the height it
implies is not a person's (a lone arm, a flickering shadow). Masks are computed at reduced
resolution (`work_scale`) for speed; boxes are returned in full frame pixels (corner convention).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calibration import Camera
from calibration.camera import fit_to_frames
from gst.data.background import BackgroundConfig, build_background, sample_indices
from gst.data.ground import ground_seed
from gst.data.masks import MaskConfig, clean_mask
from gst.detect.blazepose import as_bgr_frame
from gst.track.detection import Detection
from gst.video import END_SLACK_FRAMES, probe_video, read_frames


def group_boxes(
    boxes: np.ndarray, min_overlap: float = 0.5, max_gap: float = 0.25
) -> list[list[int]]:
    """Groups of box indices (x0, y0, x1, y1) that are pieces of one upright person: boxes are
    joined when their horizontal overlap is at least `min_overlap` of the narrower one and the
    vertical gap between them at most `max_gap` of the taller one (transitively)."""
    n = len(boxes)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            a, b = boxes[i], boxes[j]
            overlap = min(a[2], b[2]) - max(a[0], b[0])
            narrow = min(a[2] - a[0], b[2] - b[0])
            gap = max(a[1], b[1]) - min(a[3], b[3])
            tall = max(a[3] - a[1], b[3] - b[1])
            if overlap >= min_overlap * narrow and gap <= max_gap * tall:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


class StaticCameraDetector:
    """`detect(frame_bgr, frame_index) -> [Detection]` from a learnt background.

    `camera` (with the world's `up` and `floor` height) enables the standing-height check:
    a box whose bottom is inside the image must imply a height in `height_range` metres.
    """

    def __init__(
        self,
        video: str | Path,
        *,
        plate: str | Path | None = None,
        work_scale: float | None = None,
        background: BackgroundConfig | None = None,
        masks: MaskConfig | None = None,
        min_height_frac: float = 0.08,
        camera: Camera | None = None,
        up=(0.0, 0.0, 1.0),
        floor: float = 0.0,
        height_range: tuple[float, float] = (1.0, 2.4),
        group: bool = True,
    ):
        self.config = background or BackgroundConfig()
        self.mask_config = masks or MaskConfig()
        source = Path(plate) if plate is not None else Path(video)
        info = probe_video(source, source.stem, strict=True)
        # Boxes need no more than ~640 px of width: at 1080p that is 2.25x fewer pixels than
        # half size, and the background model is most of the per-frame cost.
        self.work_scale = (
            float(work_scale) if work_scale is not None else min(0.5, 640 / info.width)
        )
        self.min_height_frac = min_height_frac
        self.camera, self.up, self.floor = camera, np.asarray(up, dtype=np.float64), float(floor)
        self.height_range = height_range
        self.group = group
        if camera is not None:
            camera, _ = fit_to_frames(camera, info.width, info.height, source=str(source))
            self.camera = camera
        # the last END_SLACK_FRAMES frames a container announces may be missing (the tracking
        # loop accepts such files), so the plate is sampled before them
        sure = info.frames - END_SLACK_FRAMES if info.frames > 2 * END_SLACK_FRAMES else info.frames
        picks = sample_indices(sure, min(self.config.samples, sure))
        samples = np.stack(
            [img for _, img in read_frames(source, picks, source.stem, scale=self.work_scale)]
        )
        self.model = build_background(samples, self.config)
        self.work_size = samples.shape[2], samples.shape[1]

    def _plausible(self, box: np.ndarray, frame_h: int) -> bool:
        if box[3] - box[1] < self.min_height_frac * frame_h:
            return False
        if (
            self.camera is None or box[3] >= frame_h - 2
        ):  # feet out of view: no floor contact to use
            return True
        seed = ground_seed(self.camera, box, self.up, self.floor)
        return seed is not None and self.height_range[0] <= seed.height <= self.height_range[1]

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        # the background is BGR uint8: grey/BGRA frames failed in OpenCV, uint16 ones read as
        # all foreground (one box over the whole frame)
        frame_bgr = as_bgr_frame(frame_bgr)
        h, w = frame_bgr.shape[:2]
        small = cv2.resize(frame_bgr, self.work_size, interpolation=cv2.INTER_AREA)
        labels, blobs = clean_mask(self.model.foreground(small), self.mask_config)
        sx, sy = w / self.work_size[0], h / self.work_size[1]
        if not blobs:
            return []
        boxes = np.array(
            [
                [x * sx, y * sy, (x + bw) * sx, (y + bh) * sy]
                for x, y, bw, bh in (b.box for b in blobs)
            ]
        )
        areas = np.array([b.area for b in blobs], dtype=np.float64)
        groups = group_boxes(boxes) if self.group else [[i] for i in range(len(blobs))]
        out = []
        for g in groups:
            box = np.concatenate([boxes[g, :2].min(axis=0), boxes[g, 2:].max(axis=0)])
            if not self._plausible(box, h):
                continue
            fill = areas[g].sum() * sx * sy / max(1.0, (box[2] - box[0]) * (box[3] - box[1]))
            out.append(Detection(box=box, score=float(min(1.0, fill + 0.5))))
        return out
