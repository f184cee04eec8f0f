"""Contact sheets: every camera at one frame, optionally with the ground truth drawn on top."""

from __future__ import annotations

import cv2
import numpy as np

from calibration import Camera
from synth.projection import project_in_view
from synth.skeleton import PARENTS

_COLOURS = ((60, 220, 255), (255, 160, 60), (120, 255, 120), (255, 90, 200), (90, 120, 255))


def contact_sheet(images: list[np.ndarray], names: list[str], thumb_width: int = 480) -> np.ndarray:
    """Grid of BGR images (same order as names), each scaled to `thumb_width` and labelled."""
    if not images:
        raise ValueError("contact sheet needs at least one image")
    cols = int(np.ceil(np.sqrt(len(images))))
    rows = int(np.ceil(len(images) / cols))
    thumbs = []
    for img, name in zip(images, names, strict=True):
        h, w = img.shape[:2]
        tw = min(thumb_width, w)
        th = int(round(h * tw / w))
        t = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA) if tw != w else img.copy()
        cv2.rectangle(t, (0, 0), (min(tw, 12 + 9 * len(name)), 20), (0, 0, 0), -1)
        cv2.putText(
            t, name, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA
        )
        thumbs.append(t)
    th = max(t.shape[0] for t in thumbs)
    tw = max(t.shape[1] for t in thumbs)
    sheet = np.full((rows * th + (rows + 1) * 4, cols * tw + (cols + 1) * 4, 3), 24, np.uint8)
    for i, t in enumerate(thumbs):
        r, c = divmod(i, cols)
        y, x = 4 + r * (th + 4), 4 + c * (tw + 4)
        sheet[y : y + t.shape[0], x : x + t.shape[1]] = t
    return sheet


def truth_overlay(
    images: list[np.ndarray], cameras: list[Camera], tracks, frame: int
) -> np.ndarray:
    """Contact sheet with each person's projected skeleton and full-body box drawn in."""
    drawn = []
    for img, cam in zip(images, cameras, strict=True):
        out = img.copy()
        for k, tr in enumerate(tracks):
            colour = _COLOURS[k % len(_COLOURS)]
            uv, inside = project_in_view(cam, tr.joints[frame])
            for j, p in enumerate(PARENTS):
                if p >= 0 and inside[j] and inside[p]:
                    cv2.line(
                        out,
                        tuple(np.rint(uv[j]).astype(int)),
                        tuple(np.rint(uv[p]).astype(int)),
                        colour,
                        1,
                        cv2.LINE_AA,
                    )
            for j in np.flatnonzero(inside):
                cv2.circle(out, tuple(np.rint(uv[j]).astype(int)), 2, colour, -1, cv2.LINE_AA)
        drawn.append(out)
    return contact_sheet(drawn, [c.name for c in cameras])
