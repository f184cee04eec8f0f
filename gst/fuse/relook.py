"""A second look at crowded crops: the landmark model again, with the other people painted over.

The landmark model reads one person per region. Where two people overlap in a crop it sometimes
puts part of one person's skeleton on the other: in the lab capture cam03 sees the man from
behind beside the woman, and in frames 60-80 his right arm and leg land on her. The extraction
knows where everyone else is: the masks of their own crops of the same camera and frame. Painting
those pixels over from their surroundings (OpenCV's inpainting; never the person's own mask)
before the landmark model runs again leaves it one person to read. Dimming them instead is not
enough: the model then reads the dark figure (seen on the lab's cam03).

Every crop that other people crowd (`min_share` of its window) is read again: asking first
whether its landmarks fell on someone else misses the worst cases, where the extraction's mask
followed the wrong landmarks onto the other person. The fuse stage then lets the fitted body
judge each view read again against its first reading (`judge`; gst.fuse.consensus.
readings_against_body), because the first reading is the better one where the painting took
away what the person was hidden behind (docs/fuse.md "Crowded crops"); `first` says which of
the two readings the body is fitted from before it judges.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gst.cores import available_cores
from gst.data.store import CropStore
from gst.fuse.silhouettes import crop_windows, into_window, view_groups

__all__ = ["RelookOptions", "RelookResult", "others_masks", "relook_crowded"]


@dataclass(frozen=True)
class RelookOptions:
    min_share: float = 0.05  # other people's share of a crop window that makes it crowded
    grow: int = 3  # pixels the other people's masks are grown by before they are painted over
    refine: bool = True  # the landmark model's second pass (gst.detect.crops, refine=True)
    # after the fit, the body judges: a view read again gets its first reading back where that
    # one lies nearer the fitted body, by a factor `gain` (gst.fuse.consensus.readings_against_body)
    judge: bool = True
    gain: float = 1.0
    # the readings the first fit uses, the others then judged against it: "again" (default:
    # far better in crowds) or "stored", the extraction's (better where people seldom overlap:
    # the demo 29.2 / 25.5 mm against 30.8 / 28.9, crowd_dome_7000 59.7 against 36.3)
    first: Literal["again", "stored"] = "again"
    paint: bool = True  # paint the other people over (False: read the crowded crops again as
    # they are, the ablation that tells the painting from the second reading)


@dataclass
class RelookResult:
    landmarks: np.ndarray  # (N, 33, 3) every crop's landmarks, the crowded ones read again
    rows: np.ndarray  # (M,) the store rows that were read again
    shares: np.ndarray  # (N,) other people's share of each crop window


def others_masks(
    store: CropStore, rows: np.ndarray, windows: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """For one camera and frame (`rows` of the store): (M, S, S) bool, per crop, the pixels of
    its window that belong to another person's mask and not to its own, and (M,) their share.
    `windows`: the rows' crop windows (gst.fuse.silhouettes.crop_windows; default: read from
    the store's index, which a caller looping over every view should do once)."""
    masks = store.read_masks(rows)
    windows = crop_windows(store)[rows] if windows is None else windows
    own = masks > 127
    out = np.zeros_like(own)
    for i in range(len(rows)):
        union = np.zeros(masks.shape[1:], np.uint8)
        for j in range(len(rows)):
            if j != i:
                np.maximum(union, into_window(masks[j], windows[j], windows[i]), out=union)
        out[i] = (union > 127) & ~own[i]
    return out, out.reshape(len(rows), -1).mean(1)


def relook_crowded(
    store: CropStore,
    landmarks: np.ndarray,
    options: RelookOptions | None = None,
    model=None,
    progress=None,
    threads: int | None = None,
    cache=None,
) -> RelookResult:
    """The store's `landmarks` (N, 33, 3), with the crowded crops read again (module doc).
    `model`: a gst.detect.blazepose.BlazePose to use (then one thread); default: one per
    thread, on `threads` threads (default: the cores; the landmark model and the inpainting
    release Python's lock). `cache`: a gst.detect.reading_cache.ReadingCache (for
    `options.refine`) that gives the readings of painted crops read before and keeps the new
    ones (saved by the caller); not used with a `model` of the caller's (its readings are not
    the pipeline's model's)."""
    import cv2

    from gst.detect.blazepose import BlazePose
    from gst.detect.crops import detect_crop_landmarks

    o = options or RelookOptions()
    landmarks = np.array(landmarks, np.float32)
    if landmarks.shape != (len(store), 33, 3):
        raise ValueError(
            f"{store.path}: landmarks have shape {landmarks.shape}, expected ({len(store)}, 33, 3)"
        )
    if model is not None:
        cache = None
    kernel = np.ones((2 * o.grow + 1, 2 * o.grow + 1), np.uint8)
    windows = crop_windows(store)
    local = threading.local()

    def read(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """One camera and frame: its crops' shares of other people, and the crowded crops'
        landmarks read again (None: none crowded)."""
        try:
            return read_view(rows)
        except Exception as exc:  # raised on a pool thread: say which view
            cam = store.camera_names[int(store.index.column("camera_index")[int(rows[0])].as_py())]
            frame = int(store.index.column("frame")[int(rows[0])].as_py())
            exc.add_note(f"reading the crowded crops of camera {cam}, frame {frame} again")
            raise

    def read_view(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        others, shares = others_masks(store, rows, windows[rows])
        crowded = shares >= o.min_share
        if not crowded.any():
            return shares, crowded, None
        images = store.read_images(rows[crowded])  # BGR
        for k, mask in enumerate(others[crowded] if o.paint else []):
            grown = cv2.dilate(mask.astype(np.uint8), kernel)
            images[k] = cv2.inpaint(images[k], grown, 5, cv2.INPAINT_TELEA)
        keys = [cache.key(img) for img in images] if cache is not None else []
        readings = [cache.get(k) for k in keys] if cache is not None else [None] * len(images)
        todo = [i for i, r in enumerate(readings) if r is None]
        if todo:
            if model is None and not hasattr(local, "model"):
                local.model = BlazePose(threads=1)
            found = detect_crop_landmarks(
                images[todo], model or local.model, rgb=False, refine=o.refine
            ).with_confidence()
            for i, reading in zip(todo, found, strict=True):
                readings[i] = reading
                if cache is not None:
                    cache.put(keys[i], reading)
        return shares, crowded, np.stack(readings).astype(np.float32)

    shares = np.zeros(len(store))
    read_again: list[np.ndarray] = []
    groups = [g for g in view_groups(store) if len(g) > 1]
    workers = 1 if model is not None else (threads or available_cores())
    # one camera and frame per task, consumed in order: memory does not grow with the clip
    with ThreadPoolExecutor(workers) as pool:
        results = zip(groups, pool.map(read, groups), strict=True)
        if progress is not None:
            results = progress(results, description="crowded crops read again", total=len(groups))
        for rows, (share, crowded, found) in results:
            shares[rows] = share
            if found is not None:
                landmarks[rows[crowded]] = found
                read_again.append(rows[crowded])
    rows = np.sort(np.concatenate(read_again)) if read_again else np.zeros(0, np.int64)
    return RelookResult(landmarks, rows, shares)
