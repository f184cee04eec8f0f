"""Person ids that persist over time: online matching of ground positions (Hungarian), and an
offline pass that joins the fragments of one person."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from gst.data.association.hull import Person3D


class PersonTracker:
    """Keeps person ids stable over time by matching ground-plane positions (Hungarian).

    A person may move `max_speed * step_seconds` per step plus `slack` (silhouettes that are
    partial in some frames make the centroid jitter); ids unseen for `max_gap` steps retire.
    """

    def __init__(
        self,
        max_speed: float = 8.0,
        step_seconds: float = 1 / 30,
        slack: float = 0.3,
        max_gap: int = 15,
        first_id: int = 1,
    ):
        self.max_speed = max_speed
        self.step_seconds = step_seconds
        self.slack = slack
        self.max_gap = max_gap
        self.next_id = first_id
        self.tracks: dict[int, tuple[np.ndarray, int]] = {}  # id -> (ground position, last step)
        self.step = 0

    def update(self, persons: list[Person3D]) -> list[int]:
        """Assign ids to this step's persons (also stored in `person.person_id`)."""
        self.step += 1
        self.tracks = {i: t for i, t in self.tracks.items() if self.step - t[1] <= self.max_gap + 1}
        ids = [-1] * len(persons)
        track_ids = list(self.tracks)
        if persons and track_ids:
            pos = np.array([p.ground for p in persons])
            tpos = np.array([self.tracks[i][0] for i in track_ids])
            gap = np.array([self.step - self.tracks[i][1] for i in track_ids], dtype=float)
            cost = np.linalg.norm(pos[:, None] - tpos[None], axis=-1)
            allowed = cost <= self.slack + self.max_speed * self.step_seconds * gap[None]
            # Between two tracks in reach, prefer the one seen most recently, so a stale
            # duplicate does not steal the id back and forth.
            cost = cost + 0.1 * (gap[None] - 1)
            rows, cols = linear_sum_assignment(np.where(allowed, cost, 1e6))
            for r, c in zip(rows, cols, strict=True):
                if allowed[r, c]:
                    ids[r] = track_ids[c]
        for k, person in enumerate(persons):
            if ids[k] < 0:
                ids[k] = self.next_id
                self.next_id += 1
            person.person_id = ids[k]
            self.tracks[ids[k]] = (person.ground.copy(), self.step)
        # A track not seen this step but sitting where someone was just seen is a stale
        # duplicate of that person (a fragment that got its own id): retire it, or the two ids
        # would take turns on the same person.
        fresh = [t[0] for t in self.tracks.values() if t[1] == self.step]
        for i in [i for i, t in self.tracks.items() if t[1] < self.step]:
            if any(np.linalg.norm(self.tracks[i][0] - f) <= self.slack for f in fresh):
                del self.tracks[i]
        return ids


def link_tracklets(
    tracks: dict[int, list[tuple[int, np.ndarray]]],
    step_seconds: float,
    speed: float,
    slack: float,
    max_gap: int,
    agree: float = 0.8,
) -> dict[int, int]:
    """Join id fragments of one person, offline: returns old id -> linked id.

    `tracks` maps an id to its (step, ground position) observations. Pieces are visited in
    order of their first step. A piece joins the earlier chain it never shares a step with and
    agrees with: for at least `agree` of its observations, the chain's observation nearest in
    time is at most `max_gap` steps away and within `slack + speed * gap * step_seconds` on the
    ground. Among agreeing chains the nearest (median distance) wins. This joins a person who
    was lost and found again, and ids that took turns on one person (interleaved pieces), but
    never two people seen together. Chains keep the id of their first piece.
    """
    order = sorted(tracks, key=lambda i: (min(o[0] for o in tracks[i]), i))
    chains: list[tuple[int, np.ndarray, np.ndarray]] = []  # (id, steps sorted, positions)
    mapping: dict[int, int] = {}
    for i in order:
        obs = sorted(tracks[i], key=lambda o: o[0])
        steps = np.array([o[0] for o in obs])
        pos = np.stack([np.asarray(o[1], dtype=np.float64) for o in obs])
        best, best_d = None, np.inf
        for k, (_, c_steps, c_pos) in enumerate(chains):
            if np.isin(steps, c_steps).any():
                continue
            j = np.clip(np.searchsorted(c_steps, steps), 1, len(c_steps)) - 1
            j2 = np.minimum(j + 1, len(c_steps) - 1)
            near = np.where(np.abs(c_steps[j2] - steps) < np.abs(c_steps[j] - steps), j2, j)
            gap = np.abs(c_steps[near] - steps)
            d = np.linalg.norm(pos - c_pos[near], axis=1)
            ok = (gap <= max_gap) & (d <= slack + speed * gap * step_seconds)
            if ok.mean() >= agree and np.median(d) < best_d:
                best, best_d = k, float(np.median(d))
        if best is None:
            chains.append((i, steps, pos))
            mapping[i] = i
            continue
        cid, c_steps, c_pos = chains[best]
        merged = np.argsort(np.concatenate([c_steps, steps]), kind="stable")
        chains[best] = (
            cid,
            np.concatenate([c_steps, steps])[merged],
            np.concatenate([c_pos, pos])[merged],
        )
        mapping[i] = cid
    return mapping
