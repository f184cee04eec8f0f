"""Sampled people: body shape, outfit, motion programme and where they start in the volume."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from synth.appearance import Outfit, sample_outfit, team_kits
from synth.crowd import CrowdConfig, crowd_programme, place_crowd, walkers
from synth.motions import (
    IN_PLACE,
    LOCOMOTION,
    MOTIONS,
    MotionClip,
    generate_motion,
    random_static_poses,
)
from synth.spec import programme_problem


@dataclass(frozen=True)
class PersonSpec:
    """A person before posing. Locomotion programmes run along a loop of `1 / curvature`
    metres around the volume centre; in-place programmes start near the centre, facing it."""

    person_id: int  # 1-based, the value in masks
    betas: np.ndarray
    outfit: Outfit
    motions: tuple[str, ...]
    start: tuple[float, float]
    heading: float
    curvature: float

    def to_dict(self) -> dict:
        return {
            "person_id": self.person_id,
            "betas": [round(float(b), 6) for b in self.betas],
            "motions": list(self.motions),
            "start": [round(v, 6) for v in self.start],
            "heading": round(self.heading, 6),
            "curvature": round(self.curvature, 6),
            "outfit": self.outfit.to_dict(),
        }

    def motion_clip(self, n_frames: int, fps: float, seed: int) -> MotionClip:
        """The person's motion, deterministic from `seed` and the person id."""
        rng = np.random.default_rng(np.random.SeedSequence([seed, 2, self.person_id]))
        if self.motions == ("random_static",):
            return random_static_poses(n_frames, rng, fps=fps, start=self.start)
        return generate_motion(
            list(self.motions),
            n_frames,
            fps,
            rng,
            start=self.start,
            heading=self.heading,
            curvature=self.curvature,
        )


SAMPLED_BETAS = 10  # SMPL and GST use the first 10 shape coefficients


def sample_betas(num_betas: int, rng: np.random.Generator, scale: float = 0.8) -> np.ndarray:
    """Shape coefficients in standard deviations: the first 10 ~ N(0, scale^2) clipped to +-2.5,
    any further ones 0 (so a 10-beta model can represent every sampled body)."""
    betas = np.zeros(num_betas, np.float32)
    k = min(num_betas, SAMPLED_BETAS)
    betas[:k] = np.clip(rng.normal(0.0, scale, k), -2.5, 2.5)
    return betas


def _programme(rng: np.random.Generator, n_frames: int, fps: float) -> tuple[str, ...]:
    """A random programme: a gait, or one to three in-place sports moves (about 2 s each)."""
    n_moves = int(np.clip(round(n_frames / fps / 2.0), 1, 3))
    if rng.random() < 0.4:
        gait = [str(rng.choice(LOCOMOTION, p=[0.3, 0.5, 0.2]))]
        if n_moves > 1 and gait[0] != "sprint_start":
            gait.append(str(rng.choice(["walk", "run"])))
        return tuple(gait)
    moves = [m for m in IN_PLACE if m != "idle"]
    return tuple(str(m) for m in rng.choice(moves, size=n_moves, replace=False))


def check_programmes(n: int, programmes: Sequence[Sequence[str]] | None) -> None:
    """Refuse a people count outside 1..255 and programmes of unknown or badly mixed motions."""
    if not 1 <= n <= 255:
        raise ValueError(f"number of people must be in 1..255 (mask ids are uint8), got {n}")
    if programmes is not None and len(programmes) != n:
        raise ValueError(f"got {len(programmes)} motion programmes for {n} people")
    for i, prog in enumerate(programmes or ()):
        unknown = [m for m in prog if m not in MOTIONS and m != "random_static"]
        if not prog or unknown:
            raise ValueError(
                f"person {i + 1}: unknown motions {unknown or prog}; available: {sorted(MOTIONS)} "
                f"or ['random_static']"
            )
        if (problem := programme_problem(prog)) is not None:
            raise ValueError(f"person {i + 1}: {problem}")


def sample_people(
    n: int,
    rng: np.random.Generator,
    num_betas: int,
    volume_center: Sequence[float],
    volume_radius: float,
    n_frames: int,
    fps: float,
    programmes: Sequence[Sequence[str]] | None = None,
    n_teams: int = 2,
) -> list[PersonSpec]:
    """Sample `n` people. `programmes` optionally fixes each person's motion names (one list per
    person; 'random_static' gives independent random poses)."""
    check_programmes(n, programmes)
    kits = team_kits(max(1, n_teams), rng)
    progs = []
    for i in range(n):
        prog = tuple(programmes[i]) if programmes is not None else _programme(rng, n_frames, fps)
        check_programmes(1, [prog])
        progs.append(prog)
    cx, cy = float(volume_center[0]), float(volume_center[1])
    movers = [i for i, p in enumerate(progs) if any(m in LOCOMOTION for m in p)]
    stayers = [i for i in range(n) if i not in movers]
    loop_r = 0.6 * volume_radius
    phase0 = rng.uniform(0, 2 * np.pi)
    people = []
    for i in range(n):
        team = i % max(1, n_teams)
        outfit = sample_outfit(rng, kits[team], team)
        betas = sample_betas(num_betas, rng)
        if i in movers:
            k = movers.index(i)
            a = phase0 + 2 * np.pi * k / len(movers) + rng.uniform(-0.2, 0.2)
            start = (cx + loop_r * np.cos(a), cy + loop_r * np.sin(a))
            heading, curvature = a + np.pi / 2, 1.0 / loop_r  # counter-clockwise along the loop
        else:
            k = stayers.index(i)
            r = 0.0 if len(stayers) == 1 else 0.35 * volume_radius
            a = phase0 + np.pi / 3 + 2 * np.pi * k / max(1, len(stayers))
            start = (
                cx + r * np.cos(a) + rng.uniform(-0.1, 0.1),
                cy + r * np.sin(a) + rng.uniform(-0.1, 0.1),
            )
            # Face the centre so forward steps (kick, throw) stay in the volume.
            heading = (
                float(np.arctan2(cy - start[1], cx - start[0]))
                if r > 0
                else rng.uniform(-np.pi, np.pi)
            )
            curvature = 0.0
        people.append(
            PersonSpec(
                person_id=i + 1,
                betas=betas,
                outfit=outfit,
                motions=progs[i],
                start=(float(start[0]), float(start[1])),
                heading=float(heading),
                curvature=float(curvature),
            )
        )
    return people


def sample_crowd(
    n: int,
    rng: np.random.Generator,
    num_betas: int,
    volume_center: Sequence[float],
    volume_radius: float,
    n_frames: int,
    fps: float,
    seed: int,
    programmes: Sequence[Sequence[str]] | None = None,
    n_teams: int = 2,
    config: CrowdConfig | None = None,
) -> list[PersonSpec]:
    """Sample `n` people who crowd together (`synth.crowd`): about half walk (at least two),
    straight through the others; the rest play in-place moves a few decimetres from someone.
    `seed` is the scene seed, which fixes each person's motion (`PersonSpec.motion_clip`): the
    layout is chosen on those very motions."""
    check_programmes(n, programmes)
    kits = team_kits(max(1, n_teams), rng)
    walking = walkers(n, rng)
    people = []
    for i in range(n):
        team = i % max(1, n_teams)
        outfit = sample_outfit(rng, kits[team], team)
        betas = sample_betas(num_betas, rng)
        prog = (
            tuple(programmes[i])
            if programmes is not None
            else crowd_programme(rng, n_frames, fps, bool(walking[i]))
        )
        people.append(PersonSpec(i + 1, betas, outfit, prog, (0.0, 0.0), 0.0, 0.0))
    clips = [p.motion_clip(n_frames, fps, seed) for p in people]
    places = place_crowd(clips, rng, volume_center, volume_radius, config or CrowdConfig())
    return [
        PersonSpec(p.person_id, p.betas, p.outfit, p.motions, pl.start, pl.heading, 0.0)
        for p, pl in zip(people, places, strict=True)
    ]
