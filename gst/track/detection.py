"""Person detections and the detector protocol; `SuppliedBoxes` reads them from a file.

Boxes use the pixel-corner convention (see gst.data.crop): x0, y0, x1, y1 with x1 > x0, y1 > y0.

Supplied-box file (CSV or Parquet), one row per box:

    video   str    the video's name (its file stem); optional when the file holds one video
    frame   int    0-based frame index in the video
    x0 y0 x1 y1    box in pixels, corner convention
    score   float  optional, default 1.0
    id      int    optional, a person id given by whoever made the boxes (kept as a hint)
"""

from __future__ import annotations

import csv
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import pyarrow.parquet as pq

N_LANDMARKS = 33  # BlazePose body landmarks (MediaPipe order)


@dataclass(frozen=True, eq=False)
class Detection:
    """One person in one frame."""

    box: np.ndarray  # (4,) x0, y0, x1, y1 in px, corner convention
    score: float = 1.0
    mask: np.ndarray | None = None  # optional (H, W) bool/uint8 full-frame mask of this person
    id_hint: int | None = None  # an id supplied with the box, if any
    # optional (33, 3) BlazePose landmarks: u, v in frame pixels (pixel centres at integers) and
    # confidence in [0, 1] (visibility x presence)
    landmarks: np.ndarray | None = None

    def __post_init__(self):
        box = np.asarray(self.box, dtype=np.float64).reshape(-1)
        if box.shape != (4,) or not np.isfinite(box).all() or box[2] <= box[0] or box[3] <= box[1]:
            raise ValueError(
                f"detection box must be 4 finite numbers x0 < x1, y0 < y1, got {box.tolist()}"
            )
        object.__setattr__(self, "box", box)
        if self.landmarks is not None:
            lm = np.asarray(self.landmarks, dtype=np.float32)
            if lm.shape != (N_LANDMARKS, 3):
                raise ValueError(
                    f"detection landmarks must be ({N_LANDMARKS}, 3) u, v, confidence, got "
                    f"{lm.shape}"
                )
            object.__setattr__(self, "landmarks", lm)


@runtime_checkable
class Detector(Protocol):
    """Anything that finds people in a BGR frame."""

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]: ...


class SuppliedBoxesError(ValueError):
    """The supplied-box file is malformed; the message names the file, row and column."""


_REQUIRED = ("frame", "x0", "y0", "x1", "y1")


def _read_columns(path: Path) -> dict[str, list]:
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        try:
            return pq.read_table(path).to_pydict()
        except Exception as exc:  # pyarrow raises several types for bad files
            raise SuppliedBoxesError(f"{path}: cannot read as Parquet ({exc})") from exc
    if suffix == ".csv":
        with path.open(newline="") as fh:
            reader = csv.DictReader(fh)
            if reader.fieldnames is None:
                raise SuppliedBoxesError(
                    f"{path}: empty CSV, expected a header with {list(_REQUIRED)}"
                )
            cols: dict[str, list] = {name.strip(): [] for name in reader.fieldnames}
            for row in reader:
                if None in row:  # DictReader keeps extra fields under the key None
                    raise SuppliedBoxesError(
                        f"{path}: row {reader.line_num}: more fields than the header "
                        f"{reader.fieldnames} (a trailing comma?)"
                    )
                for name, value in row.items():
                    cols[name.strip()].append(value)
            return cols
    raise SuppliedBoxesError(
        f"{path}: unsupported box file type '{suffix}', expected .csv or .parquet"
    )


class SuppliedBoxes:
    """Detections read from a file; `detect` ignores the pixels and returns that frame's boxes."""

    def __init__(self, boxes: dict[int, list[Detection]], source: str = "<memory>"):
        self.boxes = boxes
        self.source = source

    @classmethod
    def from_file(cls, path: str | Path, video: str | None = None) -> SuppliedBoxes:
        """Load the boxes of `video` (required when the file holds several videos)."""
        path = Path(path)
        if not path.is_file():
            raise SuppliedBoxesError(f"{path}: box file not found")
        cols = _read_columns(path)
        missing = [c for c in _REQUIRED if c not in cols]
        if missing:
            raise SuppliedBoxesError(f"{path}: missing column(s) {missing}; has {sorted(cols)}")
        n = len(cols["frame"])
        videos = [str(v) for v in cols["video"]] if "video" in cols else [None] * n
        names = sorted({v for v in videos if v is not None})
        if video is None and len(names) > 1:
            raise SuppliedBoxesError(
                f"{path}: holds boxes for several videos {names}; say which one"
            )
        boxes: dict[int, list[Detection]] = defaultdict(list)
        for i in range(n):
            if video is not None and videos[i] is not None and videos[i] != video:
                continue
            where = f"{path}: row {i + 2 if path.suffix.lower() == '.csv' else i}"
            try:
                raw_frame = cols["frame"][i]
                frame = int(raw_frame)
                box = [float(cols[k][i]) for k in ("x0", "y0", "x1", "y1")]
                score = (
                    float(cols["score"][i])
                    if "score" in cols and cols["score"][i] not in ("", None)
                    else 1.0
                )
                ident = cols["id"][i] if "id" in cols else None
                ident = int(ident) if ident not in ("", None) else None
            except (TypeError, ValueError) as exc:
                raise SuppliedBoxesError(f"{where}: non-numeric value ({exc})") from exc
            # int() truncates a float (a Parquet float column): 2.7 became frame 2
            if isinstance(raw_frame, float) and raw_frame != frame:
                raise SuppliedBoxesError(f"{where}: frame must be a whole number, got {raw_frame}")
            if frame < 0:
                raise SuppliedBoxesError(f"{where}: frame must be >= 0, got {frame}")
            # a NaN score failed `score >= min_score` in the loop: the box vanished uncounted
            if not np.isfinite(score):
                raise SuppliedBoxesError(f"{where}: score must be finite, got {score}")
            try:
                boxes[frame].append(Detection(np.array(box), score, id_hint=ident))
            except ValueError as exc:
                raise SuppliedBoxesError(f"{where}: {exc}") from exc
        if video is not None and not boxes and video not in names and names:
            raise SuppliedBoxesError(
                f"{path}: no boxes for video '{video}' (videos in file: {names})"
            )
        return cls(dict(boxes), source=str(path))

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        return list(self.boxes.get(int(frame_index), ()))
