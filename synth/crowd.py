"""Crowd layouts: people who come close, cross paths and hide each other from the cameras.

The default layout (`synth.people.sample_people`) spreads runners around a loop and puts
in-place movers apart, so people rarely touch. A crowd is what breaks person extraction in
sports footage: players a few decimetres apart, walking through each other's line of sight.

`place_crowd` chooses where each person starts and which way they head, given the motion each
person will play. A motion clip played from start `s` with heading `h` (and no curvature) is the
clip played from the origin with heading 0, rotated by `h` and moved by `s`, so every candidate
placement is checked on the pelvis paths without posing a body. Person 1 stands near the middle
of the volume; each next person is anchored near someone already placed at some frame
(`approach` metres from them, random direction), with a random heading, so walkers cross the
others' paths and people in place stand in small groups. A candidate is accepted when it never
comes closer than `min_gap` to anyone (torsos would interpenetrate: collisions are not
modelled) and stays inside the volume; otherwise another is drawn (deterministic from the rng).
The rule spaces pelvises only: kicking, lunging and throwing limbs still reach into neighbours
(docs/formats/synth_scene.md measures how often).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from synth.motions import MotionClip

log = logging.getLogger("synth.crowd")


@dataclass(frozen=True)
class CrowdConfig:
    """How close a crowd is. Distances are between pelvis positions on the floor, metres."""

    approach: tuple[float, float] = (0.38, 0.5)  # distance to the anchor person at the anchor
    min_gap: float = 0.33  # closest any two people may come (about a torso's depth)
    margin: float = 0.1  # stay this far inside the volume radius
    tries: int = 400  # placements drawn per person before the best one is taken

    def __post_init__(self):
        lo, hi = self.approach
        if not 0 < self.min_gap <= lo <= hi:
            raise ValueError(
                f"crowd distances must satisfy 0 < min_gap <= approach[0] <= approach[1], "
                f"got min_gap {self.min_gap}, approach {self.approach}"
            )
        if self.tries < 1:
            raise ValueError(f"crowd tries must be >= 1, got {self.tries}")


@dataclass(frozen=True)
class Placement:
    start: tuple[float, float]
    heading: float


def crowd_programme(
    rng: np.random.Generator, n_frames: int, fps: float, walker: bool
) -> tuple[str, ...]:
    """A walker walks (turning back between walks in clips longer than about 2.5 s, so they stay
    in the volume); others play one to three in-place sports moves (about 2 s each)."""
    seconds = n_frames / fps
    if walker:
        return ("walk",) if seconds <= 2.5 else ("walk", "turn", "walk")
    moves = ["idle", "turn", "squat", "kick", "throw", "lunge", "jump"]
    n = int(np.clip(round(seconds / 2.0), 1, 3))
    return tuple(str(m) for m in rng.choice(moves, size=n, replace=False))


def walkers(n: int, rng: np.random.Generator) -> np.ndarray:
    """Which of `n` crowd members walk: at least two (so that paths cross), about half."""
    k = max(min(2, n), int(rng.binomial(n, 0.5)))
    flags = np.zeros(n, bool)
    flags[rng.choice(n, size=k, replace=False)] = True
    return flags


def _rotate(xy: np.ndarray, heading: float) -> np.ndarray:
    c, s = np.cos(heading), np.sin(heading)
    return xy @ np.array([[c, s], [-s, c]])


def path(clip: MotionClip, placement: Placement) -> np.ndarray:
    """(T, 2) pelvis path of a clip generated at the origin with heading 0, when played from
    `placement` instead."""
    return _rotate(clip.position, placement.heading) + np.asarray(placement.start)


def place_crowd(
    clips: Sequence[MotionClip],
    rng: np.random.Generator,
    center: Sequence[float],
    radius: float,
    config: CrowdConfig = CrowdConfig(),
) -> list[Placement]:
    """Start and heading of each person whose motion (generated at the origin, heading 0, no
    curvature) is `clips[k]`, so that they crowd together inside the volume (see module doc)."""
    if not clips:
        return []
    n_frames = clips[0].n_frames
    if any(c.n_frames != n_frames for c in clips):
        raise ValueError("crowd clips must all have the same number of frames")
    c = np.asarray(center[:2], np.float64)
    limit = radius - config.margin
    placed: list[np.ndarray] = []
    out: list[Placement] = []
    for clip in clips:
        best, best_score = None, -np.inf
        for _ in range(config.tries):
            heading = float(rng.uniform(-np.pi, np.pi))
            frame = int(rng.integers(n_frames // 5, n_frames - n_frames // 5 + 1))
            frame = min(frame, n_frames - 1)
            if placed:
                j = int(rng.integers(len(placed)))
                a = rng.uniform(0, 2 * np.pi)
                target = (
                    placed[j][frame] + rng.uniform(*config.approach) * np.r_[np.cos(a), np.sin(a)]
                )
            else:
                target = c + rng.uniform(0, 0.3 * radius) * _unit(rng)
            own = _rotate(clip.position, heading)
            start = target - own[frame]
            p = own + start
            # Score: how far inside every constraint the candidate is (>= 0 means accepted).
            inside = limit - float(np.linalg.norm(p - c, axis=1).max())
            gap = min((float(np.linalg.norm(p - q, axis=1).min()) for q in placed), default=1.0)
            score = min(inside, gap - config.min_gap)
            if score > best_score:
                best, best_score = Placement((float(start[0]), float(start[1])), heading), score
            if score >= 0:
                break
        if best_score < 0:  # kept the least bad: said, never silent (30 people in a 1.5 m room)
            log.warning(
                "crowd layout: person %d could not be placed within the rules after %d tries "
                "(%s); kept the best placement found",
                len(out) + 1,
                config.tries,
                f"{-best_score:.2f} m short of {config.min_gap} m from the others or "
                f"{config.margin} m inside the volume",
            )
        placed.append(path(clip, best))
        out.append(best)
    return out


def _unit(rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    return np.r_[np.cos(a), np.sin(a)]


def closest_approach(paths: Sequence[np.ndarray]) -> np.ndarray:
    """(n, n) closest distance between each two pelvis paths (T, 2) over the clip (inf on the
    diagonal)."""
    n = len(paths)
    out = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            out[i, j] = out[j, i] = float(np.linalg.norm(paths[i] - paths[j], axis=1).min())
    return out


__all__ = [
    "CrowdConfig",
    "Placement",
    "closest_approach",
    "crowd_programme",
    "path",
    "place_crowd",
    "walkers",
]
