"""Single-frame spikes of a fitted limb (gst.fuse.spikes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body import load_body_model
from gst.body.markers import MarkerModel
from gst.fuse.fit import PersonFit, fit_people
from gst.fuse.spikes import drop_spikes, spiking_landmarks
from gst.fuse.triangulate import triangulate_person
from tests.fuse_fixtures import make_capture, observations


def _fit(markers: np.ndarray, frames: np.ndarray) -> PersonFit:
    T, M = markers.shape[:2]
    z = np.zeros
    return PersonFit(
        1, frames, z(10), z((T, 3)), z((T, 23, 3)), z((T, 3)), z((T, 24, 3)), markers,
        z((T, 1, M)), np.ones(T, bool), z(T, bool), False, 1.0,
    )  # fmt: skip


def _smooth(T: int, M: int, rng: np.random.Generator, accel: float) -> np.ndarray:
    """Markers moving with a constant velocity and a constant acceleration whose second
    difference per frame is `accel` metres."""
    t = np.arange(T, dtype=np.float64)[:, None, None]
    x0, v = rng.normal(0, 1, (1, M, 3)), rng.normal(0, 0.05, (1, M, 3))
    a = rng.normal(0, 1, (1, M, 3))
    a *= accel / np.linalg.norm(a, axis=-1, keepdims=True)
    return x0 + v * t + 0.5 * a * t**2


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), T=st.integers(5, 30), fps=st.sampled_from([30.0, 60.0]))
def test_a_single_frame_jump_is_flagged_alone(seed, T, fps):
    """Smooth motion with a second difference below the bound (0.25 m at 30 fps is a midpoint
    deviation, half a second difference) is never flagged; one marker moved `jump` times the
    bound in one frame with two frames on either side is flagged there and nowhere else."""
    rng = np.random.default_rng(seed)
    accel, jump = rng.uniform(0.0, 0.4), rng.uniform(1.1, 3.0)
    bound = 0.25 * (30.0 / fps) ** 2
    X = _smooth(T, 5, rng, accel * bound)  # midpoint deviation accel / 2 x bound
    frames = np.arange(T) + 7
    assert not spiking_landmarks(_fit(X, frames), 0.25, fps).any()
    t, m = int(rng.integers(2, T - 2)), int(rng.integers(0, 5))
    d = rng.normal(0, 1, 3)
    X[t, m] += (jump + accel) * bound * d / np.linalg.norm(d)
    flag = spiking_landmarks(_fit(X, frames), 0.25, fps)
    assert flag[t, m] and flag.sum() == 1


def test_frames_without_both_neighbours_are_not_judged():
    X = np.zeros((5, 2, 3))
    X[2, 0] = 5.0  # a jump at frame 12, whose neighbour frame 13 is missing
    frames = np.array([10, 11, 12, 14, 15])
    assert not spiking_landmarks(_fit(X, frames), 0.25, 30.0).any()
    assert spiking_landmarks(_fit(X, np.arange(5)), 0.25, 30.0)[2, 0]


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


def test_a_leg_misread_in_every_view_of_one_frame_is_refitted_from_its_neighbours(body):
    """Every camera reads the right leg's landmarks of frame 4 0.7 m to the side (consistently,
    as the landmark model does for a fast kick): the fit follows them; with the frame's spiking
    landmarks dropped and refitted, the leg lies near the truth again and the other frames and
    landmarks are untouched."""
    cap = make_capture(body, n_people=1, n_frames=9, n_cams=4, seed=3)
    leg = [26, 28, 30, 32]  # right knee, ankle, heel, foot index
    misread = cap.markers.copy()
    misread[0, 4, leg] += [0.5, 0.5, 0.0]
    people = observations(dataclasses.replace(cap, markers=misread), noise_px=0.5, seed=1)
    markers = MarkerModel.load()
    tris = [triangulate_person(p) for p in people]
    fits = fit_people(body, markers, people, tris, fps=30.0)
    ankle = 8  # SMPL right_ankle

    def ankle_error(f: PersonFit) -> float:
        return float(np.linalg.norm(f.joints[4, ankle] - cap.joints[0, 4, ankle]))

    assert ankle_error(fits[0]) > 0.3
    dropped, n = drop_spikes(people, fits, 0.25, 30.0)
    zeroed = (people[0].confidence > 0) & (dropped[0].confidence == 0)
    assert n > 0 and zeroed[4].any() and not np.delete(zeroed, 4, axis=0).any()
    assert set(np.nonzero(zeroed[4])[1]) <= set(leg)
    refit = fit_people(body, markers, dropped, [triangulate_person(p) for p in dropped], 30.0)
    assert ankle_error(refit[0]) < 0.1
