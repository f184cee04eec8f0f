"""Single-frame spikes of a fitted limb: a marker that jumps far from where its neighbouring
frames put it and comes straight back.

The landmark model now and then reads a fast limb wrong in most views of one frame, the same
way (the demo's person 2 kicking backwards at frame 20: the right ankle triangulated 0.77 m from
where frames 19 and 21 put it, and the fitted foot 1.1 m from the truth). The fit's smoothness
term is robust (Cauchy), so it lets such a frame go. A marker whose fitted position lies further
than `spike_m` (at 30 fps; scaled by (30 / fps)^2, as a second difference is) from the midpoint
of its neighbours, more than at either neighbour, implies an acceleration no body part reaches
outside an impact (0.25 m: about 45 g), so its landmarks in that frame are taken as no reading
and the refit fills them from the neighbouring frames and the rest of the body.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gst.fuse.fit import PersonFit
from gst.fuse.observations import PersonObservations

__all__ = ["spiking_landmarks", "drop_spikes"]


def spiking_landmarks(fit: PersonFit, spike_m: float, fps: float) -> np.ndarray:
    """(T, M) bool over `fit.frames`: markers that spike (module doc). Only frames with two
    consecutive fitted frames on either side are judged."""
    X, f = np.asarray(fit.markers, np.float64), np.asarray(fit.frames)
    out = np.zeros(X.shape[:2], bool)
    if len(f) < 3:
        return out
    dev = np.zeros(X.shape[:2])
    dev[1:-1] = np.linalg.norm(X[1:-1] - 0.5 * (X[:-2] + X[2:]), axis=-1)
    centred = np.zeros(len(f), bool)
    centred[1:-1] = (f[1:-1] - f[:-2] == 1) & (f[2:] - f[1:-1] == 1)
    dev[~centred] = 0.0
    # the frame that jumped, not its neighbours (whose midpoints hold the jump too); judged only
    # where both neighbours have both of theirs as well (next to a clip's end or a gap, a jump
    # of the frame that cannot be judged would look like its neighbour's)
    judged = np.zeros(len(f), bool)
    judged[1:-1] = centred[:-2] & centred[1:-1] & centred[2:]
    peak = np.zeros_like(out)
    peak[1:-1] = (dev[1:-1] > dev[:-2]) & (dev[1:-1] >= dev[2:])
    return judged[:, None] & peak & (dev > spike_m * (30.0 / fps) ** 2)


def drop_spikes(
    people: list[PersonObservations], fits: list[PersonFit], spike_m: float, fps: float
) -> tuple[list[PersonObservations], int]:
    """Each person's observations with the landmarks of spiking markers given no confidence in
    every view of that frame; and how many (frame, landmark) pairs that was."""
    out, total = [], 0
    for p, fit in zip(people, fits, strict=True):
        flag = spiking_landmarks(fit, spike_m, fps)[np.searchsorted(fit.frames, p.frames)]
        n = int(flag.sum())
        total += n
        if n:
            conf = p.confidence.copy()
            conf[np.broadcast_to(flag[:, None, :], conf.shape)] = 0.0
            p = replace(p, confidence=conf)
        out.append(p)
    return out, total
