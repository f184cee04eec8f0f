"""Procedural motions: joint limits, smoothness in time, feet on the floor, body-model rests."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from synth_fixtures import CapsuleBody

from synth.animate import FLOOR_TOLERANCE, pose_person
from synth.motions import LOCOMOTION, MOTIONS, generate_motion, random_static_poses
from synth.skeleton import (
    JOINT_LIMITS,
    JOINT_NAMES,
    PARENTS,
    J,
    mirror_angles,
    rest_corrections,
    soft_clip,
)

BODY = CapsuleBody(max_edge=0.12)  # coarse mesh: motion tests need joints and feet, not detail
FOOT = np.isin(BODY.part_labels, [BODY.part_names.index("foot")])


def _posed(name, seed, n=60, fps=30.0):
    clip = generate_motion(name, n, fps, np.random.default_rng(seed))
    betas = np.random.default_rng(seed + 100).normal(0, 0.8, 10)
    return clip, pose_person(BODY, betas, clip, 1)


@settings(max_examples=20, deadline=None)
@given(name=st.sampled_from(sorted(MOTIONS)), seed=st.integers(0, 1000))
def test_angles_stay_within_joint_limits(name, seed):
    clip = generate_motion(name, 45, 30.0, np.random.default_rng(seed))
    lo, hi = JOINT_LIMITS[..., 0], JOINT_LIMITS[..., 1]
    assert np.all(clip.angles >= lo - 1e-9) and np.all(clip.angles <= hi + 1e-9)
    # The posed skeleton agrees: elbows and knees bend at most 150 degrees (limits + noise).
    tr = pose_person(BODY, np.zeros(10), clip, 1)
    for a, b, c in (("shoulder", "elbow", "wrist"), ("hip", "knee", "ankle")):
        for side in ("left", "right"):
            u = tr.joints[:, J[f"{side}_{b}"]] - tr.joints[:, J[f"{side}_{a}"]]
            v = tr.joints[:, J[f"{side}_{c}"]] - tr.joints[:, J[f"{side}_{b}"]]
            cos = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
            assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() <= 151, (
                f"{side} {b} over-bent in {name}"
            )


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_feet_on_the_floor_and_knees_bend_forward(name):
    clip, tr = _posed(name, seed=3)
    lowest = tr.vertices[..., 2].min(axis=1)
    assert lowest.min() >= -FLOOR_TOLERANCE - 1e-5, "body sinks into the floor"
    # Stance: no flight within 0.1 s (take-off and landing are smoothed over ~50 ms).
    flight = clip.lift > 1e-6
    near_flight = np.convolve(flight.astype(float), np.ones(7), mode="same") > 0
    grounded = ~near_flight
    assert np.all(lowest[grounded] < 0.02), "stance frames float above the floor"
    # The lowest point of the body is a foot (sprint start may rest on the hands).
    low_vertex = tr.vertices[..., 2].argmin(axis=1)
    if name != "sprint_start":
        assert FOOT[low_vertex].mean() > 0.95
    # No knee hyperextension: the shin folds backwards relative to the thigh.
    left_axis = tr.joints[:, J["left_hip"]] - tr.joints[:, J["right_hip"]]
    for side in ("left", "right"):
        hip, knee, ankle = (tr.joints[:, J[f"{side}_{k}"]] for k in ("hip", "knee", "ankle"))
        fold = (np.cross(knee - hip, ankle - knee) * left_axis).sum(-1)
        assert fold.min() > -1e-4, f"{side} knee bends backwards in {name}"


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_motion_is_smooth_in_time(name):
    """Sampled 4x finer, the acceleration estimate of a smooth (C1) motion stays put, while a
    jump in position or velocity would grow 16x or 4x."""
    acc = []
    for fps in (30.0, 120.0):
        clip = generate_motion(name, int(3 * fps), fps, np.random.default_rng(11))
        tr = pose_person(BODY, np.zeros(10), clip, 1)
        acc.append(np.linalg.norm(np.diff(tr.joints, 2, axis=0), axis=-1).max() * fps**2)
    assert acc[1] < 1.6 * acc[0], (
        f"{name}: acceleration {acc[0]:.0f} -> {acc[1]:.0f} m/s^2 when sampled finer"
    )
    assert acc[0] < 700, f"{name}: implausible peak joint acceleration {acc[0]:.0f} m/s^2"


def test_programme_crossfades_smoothly_and_labels_frames():
    fps = 30.0
    accs = []
    for f in (fps, 4 * fps):
        clip = generate_motion(["squat", "kick", "turn"], int(6 * f), f, np.random.default_rng(5))
        tr = pose_person(BODY, np.zeros(10), clip, 1)
        accs.append(np.linalg.norm(np.diff(tr.joints, 2, axis=0), axis=-1).max() * f**2)
    assert accs[1] < 1.6 * accs[0]
    assert set(clip.labels) == {"squat", "kick", "turn"}
    assert clip.labels[0] == "squat" and clip.labels[-1] == "turn"


def test_locomotion_moves_and_curves():
    clip = generate_motion(
        "run",
        90,
        30.0,
        np.random.default_rng(1),
        start=(1.0, 0.0),
        heading=np.pi / 2,
        curvature=1.0,
    )
    speed = np.linalg.norm(np.diff(clip.position, axis=0), axis=1).mean() * 30
    assert 2.0 < speed < 4.5
    # On a unit-curvature loop around the origin the runner stays ~1 m from it.
    r = np.linalg.norm(clip.position, axis=1)
    assert np.all(np.abs(r - 1.0) < 0.1)
    assert set(LOCOMOTION) <= set(MOTIONS)


def test_generation_is_deterministic_and_varies_per_person():
    a = generate_motion("jump", 30, 30.0, np.random.default_rng(4))
    b = generate_motion("jump", 30, 30.0, np.random.default_rng(4))
    c = generate_motion("jump", 30, 30.0, np.random.default_rng(5))
    assert np.array_equal(a.angles, b.angles)
    assert not np.allclose(a.angles, c.angles)


def test_random_static_poses_span_the_limits():
    clip = random_static_poses(200, np.random.default_rng(0))
    assert not clip.smooth and clip.labels[0] == "random_static"
    lo, hi = JOINT_LIMITS[..., 0], JOINT_LIMITS[..., 1]
    assert np.all(clip.angles >= lo - 1e-9) and np.all(clip.angles <= hi + 1e-9)
    knee = clip.angles[:, J["left_knee"], 0]
    assert knee.max() - knee.min() > np.deg2rad(60)
    tr = pose_person(BODY, np.zeros(10), clip, 1)
    assert tr.vertices[..., 2].min() >= -1e-5  # unsmoothed: exactly on the floor
    assert np.allclose(tr.vertices[..., 2].min(axis=1), 0, atol=1e-5)


def test_a_pose_rest_gives_the_same_motion_as_t_pose():
    """Anny rests in an A-pose; the rest correction makes authored angles mean the same."""
    clip = generate_motion("throw", 40, 30.0, np.random.default_rng(2))
    t_pose = pose_person(CapsuleBody("T"), np.zeros(10), clip, 1)
    a_pose = pose_person(CapsuleBody("A"), np.zeros(10), clip, 1)
    assert np.abs(t_pose.joints - a_pose.joints).max() < 1e-4
    C = rest_corrections(a_pose.rest_joints)
    assert np.degrees(Rotation.from_matrix(C[J["left_shoulder"]]).magnitude()) == pytest.approx(
        45, abs=0.5
    )
    # The stand-in T-pose has slightly tilted shins (6 degrees) and arms (2): only that is
    # corrected.
    assert (
        np.degrees(Rotation.from_matrix(rest_corrections(t_pose.rest_joints)).magnitude()).max() < 7
    )


def test_body_parameters_reproduce_the_world_joints():
    clip, tr = _posed("kick", seed=9, n=20)
    import torch

    out = BODY(
        betas=torch.from_numpy(np.repeat(tr.betas[None], 20, 0)),
        body_pose=torch.from_numpy(tr.body_pose),
        global_orient=torch.from_numpy(tr.global_orient),
        transl=torch.from_numpy(tr.transl),
    )
    assert np.abs(out.joints.numpy() - tr.joints).max() < 1e-5
    # The pelvis follows the motion's path in the world.
    assert np.abs(tr.joints[:, 0, :2] - clip.position).max() < 1e-4


def test_mirroring_swaps_sides():
    a = np.zeros((1, 24, 3))
    a[0, J["left_hip"]] = [0.1, 0.2, 0.3]
    m = mirror_angles(a)
    assert np.allclose(m[0, J["right_hip"]], [0.1, -0.2, -0.3]) and np.allclose(
        m[0, J["left_hip"]], 0
    )
    assert np.allclose(mirror_angles(m), a)
    assert JOINT_NAMES[PARENTS[J["left_knee"]]] == "left_hip"


@settings(max_examples=50, deadline=None)
@given(x=st.floats(-10, 10), lo=st.floats(-3, 0), width=st.floats(0.1, 4))
def test_soft_clip_is_bounded_monotone_and_identity_inside(x, lo, width):
    hi = lo + width
    y = soft_clip(np.array([x, x + 1e-3]), np.array(lo), np.array(hi))
    assert lo - 1e-12 <= y[0] <= hi + 1e-12
    assert y[1] >= y[0] - 1e-12
    k = min(np.deg2rad(8), 0.25 * width)
    if lo + k <= x <= hi - k:
        assert y[0] == pytest.approx(x)
