"""Synthetic people for the crowd tests: BlazePose's 33 landmarks of a standing person in the
world, projected into a synthetic rig as detector-like instances (noise, dropouts, NaN)."""

from __future__ import annotations

import numpy as np

from gst.data.keypoints import N_LANDMARKS, PersonInstance
from synth.rigs import make_rig

# A 1.75 m person facing +y in a body frame (x = body left, y = forward, z = up), metres.
_TEMPLATE = {
    0: (0.0, 0.10, 1.62),  # nose
    1: (0.03, 0.09, 1.66),
    2: (0.035, 0.085, 1.66),
    3: (0.045, 0.08, 1.66),
    4: (-0.03, 0.09, 1.66),
    5: (-0.035, 0.085, 1.66),
    6: (-0.045, 0.08, 1.66),
    7: (0.075, 0.02, 1.63),
    8: (-0.075, 0.02, 1.63),  # ears
    9: (0.02, 0.09, 1.57),
    10: (-0.02, 0.09, 1.57),  # mouth
    11: (0.19, 0.0, 1.43),
    12: (-0.19, 0.0, 1.43),  # shoulders
    13: (0.24, 0.02, 1.15),
    14: (-0.24, 0.02, 1.15),  # elbows
    15: (0.26, 0.08, 0.90),
    16: (-0.26, 0.08, 0.90),  # wrists
    17: (0.27, 0.10, 0.82),
    18: (-0.27, 0.10, 0.82),
    19: (0.25, 0.12, 0.82),
    20: (-0.25, 0.12, 0.82),
    21: (0.24, 0.11, 0.86),
    22: (-0.24, 0.11, 0.86),
    23: (0.10, 0.0, 0.92),
    24: (-0.10, 0.0, 0.92),  # hips
    25: (0.11, 0.03, 0.50),
    26: (-0.11, 0.03, 0.50),  # knees
    27: (0.11, -0.01, 0.08),
    28: (-0.11, -0.01, 0.08),  # ankles
    29: (0.11, -0.06, 0.03),
    30: (-0.11, -0.06, 0.03),  # heels
    31: (0.12, 0.15, 0.02),
    32: (-0.12, 0.15, 0.02),  # toes
}
TEMPLATE = np.array([_TEMPLATE[k] for k in range(N_LANDMARKS)], np.float64)


def person(x: float, y: float, heading: float = 0.0, height: float = 1.75, pose=None):
    """(33, 3) world landmarks of a person standing at (x, y) facing `heading` (radians from +x),
    scaled to `height`; `pose` (33, 3) adds offsets in the body frame."""
    body = TEMPLATE * (height / 1.75) + (0 if pose is None else pose)
    a = heading - np.pi / 2  # the template faces +y
    c, s = np.cos(a), np.sin(a)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return body @ R.T + np.array([x, y, 0.0])


def rig(kind: str = "dome", n: int = 7, seed: int = 0):
    return make_rig(kind, n, 480, 360, distortion="mild", fps=30.0, seed=seed)


def instances(
    rig_,
    people: list[np.ndarray],
    noise_px: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
    cameras: dict[int, list[str]] | None = None,
) -> tuple[dict[str, list[PersonInstance]], dict[str, list[int]]]:
    """Each camera's instances of `people` (list of (33, 3) world landmarks), shuffled per
    camera, with pixel noise and dropouts (confidence 0). `cameras` optionally limits person k
    to those camera names. Returns (instances, truth) where truth[camera][i] is the person index
    of instance i."""
    rng = np.random.default_rng(seed)
    out, truth = {}, {}
    for cam in rig_:
        found = []
        for k, pts in enumerate(people):
            if cameras is not None and k in cameras and cam.name not in cameras[k]:
                continue
            uv = cam.project(pts) + rng.normal(0, noise_px, (N_LANDMARKS, 2))
            inside = (
                (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
            )
            if inside.mean() < 0.5:
                continue
            conf = rng.uniform(0.6, 1.0, N_LANDMARKS) * (rng.random(N_LANDMARKS) >= dropout)
            lm = np.c_[uv, conf]
            found.append((k, PersonInstance.create(lm, where=f"camera {cam.name}, person {k}")))
        order = rng.permutation(len(found))
        out[cam.name] = [found[i][1] for i in order]
        truth[cam.name] = [found[i][0] for i in order]
    return out, truth


def walker_observations(n_frames: int = 5, n_cams: int = 5):
    """`PersonObservations` of one person walking, seen by `n_cams` synthetic cameras in
    full-image pixels (identity crops), confidence 0.9 everywhere."""
    from gst.fuse.observations import PersonObservations

    cams = list(rig("dome", n_cams, seed=1))
    T, C = n_frames, len(cams)
    uv = np.stack([[c.project(person(0.02 * t, 0.0)) for c in cams] for t in range(T)])
    K = np.broadcast_to(np.stack([c.K for c in cams]), (T, C, 3, 3)).copy()
    Rt = np.broadcast_to(np.stack([np.c_[c.R, c.t] for c in cams]), (T, C, 3, 4)).copy()
    conf, scale = np.full((T, C, N_LANDMARKS), 0.9), np.ones((T, C))
    return PersonObservations(1, np.arange(T), uv, conf, K, Rt, scale, np.zeros((T, C), np.int64))
