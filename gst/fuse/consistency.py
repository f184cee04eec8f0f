"""How steady the rig's 3D is: limb lengths measured frame by frame, with the shape left free.

The clip's body fit has one shape per person, so its bone lengths are constant by construction
and say nothing about the data. Here every observed person-frame is fitted on its own (same
energy, no temporal term, its own betas under a weak prior), and the lengths of the eight limb
segments of that frame's skeleton are taken: their coefficient of variation over the clip
measures the evidence. It is steadier than the distance between two triangulated landmarks
(which carries both landmarks' noise) because a frame's shape is pinned by all its landmarks in
all views at once, yet nothing ties one frame's lengths to another's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gst.body.markers import MarkerModel
from gst.body.model import BodyModel
from gst.fuse.fit import FitOptions, fit_people
from gst.fuse.observations import PersonObservations
from gst.fuse.start import TORSO_LANDMARKS
from gst.fuse.triangulate import PersonTriangulation

__all__ = ["LIMB_SEGMENTS", "per_frame_limb_lengths"]

# SMPL joint pairs of the limb segments
LIMB_SEGMENTS: dict[str, tuple[int, int]] = {
    "left_upper_arm": (16, 18),
    "left_forearm": (18, 20),
    "left_thigh": (1, 4),
    "left_shin": (4, 7),
    "right_upper_arm": (17, 19),
    "right_forearm": (19, 21),
    "right_thigh": (2, 5),
    "right_shin": (5, 8),
}


def per_frame_limb_lengths(
    body: BodyModel,
    markers: MarkerModel,
    people: list[PersonObservations],
    tris: list[PersonTriangulation | None],
    fps: float,
    options: FitOptions | None = None,
    w_betas: float = 0.1,
    marker_offsets: list[np.ndarray | None] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Per person: segment name -> (T,) lengths in metres over the person's frames (NaN where
    the torso was not triangulated). `marker_offsets`: each person's own marker corrections
    from the clip's fit (PersonFit.marker_offsets), held fixed: a frame's shape must not hide
    in its markers."""
    o = replace(
        options or FitOptions(), w_smooth=0.0, w_betas=w_betas, max_gap_s=0.0, w_marker_offsets=0.0
    )
    own = marker_offsets or [None] * len(people)
    singles, singles_tri, where, single_offsets = [], [], [], []
    for k, (p, tri) in enumerate(zip(people, tris, strict=True)):
        torso = (
            tri.points[:, list(TORSO_LANDMARKS)] if tri is not None else np.full((1, 4, 3), np.nan)
        )
        for t in np.flatnonzero(np.isfinite(torso).all(-1).sum(-1) >= 3):  # a triangulated torso
            keep = np.zeros(len(p.frames), bool)
            keep[t] = True
            singles.append(replace(p.select(keep), person_id=len(singles)))
            singles_tri.append(_select_tri(tri, keep) if tri is not None else None)
            where.append((k, t))
            single_offsets.append(own[k])
    out = [{name: np.full(len(p.frames), np.nan) for name in LIMB_SEGMENTS} for p in people]
    if not singles:
        return out
    fits = fit_people(body, markers, singles, singles_tri, fps, o, marker_offsets=single_offsets)
    for (k, t), f in zip(where, fits, strict=True):
        for name, (a, b) in LIMB_SEGMENTS.items():
            out[k][name][t] = np.linalg.norm(f.joints[0, a] - f.joints[0, b])
    return out


def _select_tri(tri: PersonTriangulation, keep: np.ndarray) -> PersonTriangulation:
    return PersonTriangulation(
        tri.points[keep], tri.used[keep], tri.errors[keep], tri.error[keep], tri.confidence[keep]
    )
