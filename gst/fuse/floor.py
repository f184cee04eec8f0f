"""The ground under the fitted bodies: how high each marker must stay above it, and whether the
rig's world has its floor at height 0.

Nobody's heel sinks into the floor, yet 2D landmarks alone let a fitted foot dip a few cm below
it where the views disagree (on the tuning worlds 5 % of the fitted foot joints lay below the
ground). The fit's floor term (gst.fuse.objective.Floor) holds each foot marker at least its rest
height above the soles, every other marker above the floor itself. Worlds made by the calibrate
stage, and the z-up worlds of the imported formats (H36M, Qualisys, Pose2Sim), put the floor at
height 0 along the rig's up axis; others (a world centred on a camera) do not, so by default the
floor is used only where the people's triangulated feet stand near height 0 (`world_floor`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Literal

import numpy as np

from gst.body.markers import BLAZEPOSE_NAMES, MarkerModel
from gst.body.model import BodyModel

__all__ = [
    "FOOT_MARKERS",
    "FLOOR_SEARCH_M",
    "contact_height",
    "floor_clearance",
    "scene_floor",
    "stands_on",
    "world_floor",
]

FOOT_MARKERS = ("ankle", "heel", "foot_index")  # marker name endings held at their rest height
FLOOR_SEARCH_M = 0.15  # the feet must stand this close to height 0 for it to be the floor
_SOLES = [  # the landmarks of the soles: heels and foot indices
    BLAZEPOSE_NAMES.index(f"{s}_{p}") for s in ("left", "right") for p in ("heel", "foot_index")
]


def floor_clearance(
    body: BodyModel, markers: MarkerModel, rest_markers: np.ndarray, tolerance: float
) -> np.ndarray:
    """(M,) each marker's lowest height above the floor: for the feet's markers their height
    above the soles when the mean body stands (`rest_markers`, body frame; SMPL-layout bodies
    stand along +Y), less `tolerance`; every other marker just stays above the floor."""
    sole = float(body.v_template[:, 1].min())
    feet = np.array([any(n.endswith(f) for f in FOOT_MARKERS) for n in markers.names])
    return np.where(feet, np.maximum(rest_markers[:, 1] - sole - tolerance, 0.0), 0.0)


def contact_height(points: Sequence[np.ndarray | None], up: np.ndarray) -> float:
    """Median over person-frames of the lowest triangulated heel or foot index along `up`
    (metres; NaN when no foot was triangulated). `points`: per person (T, 33, 3) world."""
    lows = []
    for p in points:
        if p is None or not len(p):
            continue
        h = np.asarray(p, np.float64)[:, _SOLES] @ np.asarray(up, np.float64)
        seen = np.isfinite(h).any(1)
        lows.append(np.nanmin(h[seen], axis=1))
    lows = np.concatenate(lows) if lows else np.zeros(0)
    return float(np.median(lows)) if len(lows) else float("nan")


def world_floor(points: Sequence[np.ndarray | None], up: np.ndarray) -> tuple[float | None, float]:
    """(0.0 if the world's height 0 is where the people stand, else None; the measured median
    contact height). Feet are a few cm above the floor at most when planted, so a median within
    FLOOR_SEARCH_M of 0 says the floor is there."""
    h = contact_height(points, up)
    return (0.0 if np.isfinite(h) and abs(h) <= FLOOR_SEARCH_M else None), h


def stands_on(points: np.ndarray | None, up: np.ndarray, height: float) -> bool:
    """Whether a person's triangulated soles (`points` (T, 33, 3) world, or None) stand near the
    floor at `height` along `up` (within FLOOR_SEARCH_M, median over their frames); True when
    none were triangulated (the floor's default). The lab's two people stand on a force plate
    at height 0 and its bystander on the room's floor, 0.18 m below: held above height 0, her
    fitted shank shrank to 0.19 m (0.35 m between her triangulated knee and ankle)."""
    h = contact_height([points], up)
    return not np.isfinite(h) or abs(h - height) <= FLOOR_SEARCH_M


def scene_floor(
    points: Sequence[np.ndarray | None],
    up: np.ndarray,
    height: float | Literal["auto"] | None,
    person_ids: Sequence[int] | None = None,
    log: logging.Logger | None = None,
) -> tuple[np.ndarray, float] | None:
    """The fit's floor, (up, height along it), or None for no floor term, as the fuse stage's
    `floor` option asks: a height, None, or "auto" (`world_floor` on the triangulated people,
    `points` per person (T, 33, 3) world or None). Logs where the feet stand and who stands on
    other ground (the fit leaves those without the floor term, `stands_on`)."""
    up = np.asarray(up, np.float64)
    if height == "auto":
        height, contact = world_floor(points, up)
        if log is not None and not np.isfinite(contact):
            log.info("fuse: no triangulated feet to find the floor by: no floor term")
        elif log is not None:
            log.info(
                "fuse: feet stand a median %.3f m above the world's height 0: %s", contact,
                "the floor term holds them above it" if height is not None else "no floor term",
            )  # fmt: skip
    if height is None:
        return None
    if log is not None:
        ids = range(len(points)) if person_ids is None else person_ids
        elsewhere = [
            f"person {i} ({contact_height([x], up) - height:+.2f} m)"
            for i, x in zip(ids, points, strict=True)
            if x is not None and not stands_on(x, up, float(height))
        ]
        if elsewhere:
            log.info(
                "fuse: people standing on other ground than the floor (their soles' median "
                "height against it), fitted without the floor term: %s", ", ".join(elsewhere),
            )  # fmt: skip
    return up, float(height)
