"""gst.track.align: the lateral shift that puts a body on its landmarks. Landmarks are made with
OpenCV's projection (an independent reference), from the body moved by a known shift."""

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body.markers import BLAZEPOSE_NAMES
from gst.track.agreement import COMPARED_JOINTS
from gst.track.align import AlignmentConfig, align_translation
from gst.track.schema import SMPL_JOINT_NAMES

K = np.array([[300.0, 0, 128.0], [0, 300.0, 128.0], [0, 0, 1]])


def _body(depth: float, rng: np.random.Generator) -> np.ndarray:
    joints = rng.normal(0, 0.3, (24, 3)) * [1, 2.5, 0.5]
    joints[:, 2] += depth
    # the pelvis is the hips' mean (its landmark target), the hips at one depth so that the mean
    # of their projections is the projection of their mean
    hips = [SMPL_JOINT_NAMES.index("left_hip"), SMPL_JOINT_NAMES.index("right_hip")]
    joints[hips[1], 2] = joints[hips[0], 2]
    joints[SMPL_JOINT_NAMES.index("pelvis")] = joints[hips].mean(0)
    return joints


def _landmarks(joints: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """BlazePose-layout landmarks where the shifted body's compared joints project (both hips
    of the pelvis pair at the pelvis), confidence 1, the rest NaN."""
    lm = np.full((33, 3), np.nan)
    pts, _ = cv2.projectPoints(joints + shift, np.zeros(3), np.zeros(3), K, None)
    for joint, names in COMPARED_JOINTS.items():
        if joint == "pelvis":
            continue  # the hips carry it (the pelvis is their mean)
        lm[BLAZEPOSE_NAMES.index(names[0])] = [*pts[SMPL_JOINT_NAMES.index(joint), 0], 1.0]
    return lm


@settings(max_examples=40, deadline=None)
@given(
    dx=st.floats(-0.4, 0.4),
    dy=st.floats(-0.4, 0.4),
    depth=st.floats(2.0, 12.0),
    seed=st.integers(0, 2**16),
)
def test_recovers_a_lateral_shift(dx, dy, depth, seed):
    joints = _body(depth, np.random.default_rng(seed))
    lm = _landmarks(joints, np.array([dx, dy, 0.0]))
    t = align_translation(joints[None], K[None], lm[None])[0]
    np.testing.assert_allclose(t, [dx, dy, 0.0], atol=1e-6)


def test_an_outlier_landmark_barely_moves_the_body():
    rng = np.random.default_rng(3)
    joints = _body(4.0, rng)
    lm = _landmarks(joints, np.zeros(3))
    lm[BLAZEPOSE_NAMES.index("right_wrist"), :2] += 300.0  # one joint far off
    t = align_translation(joints[None], K[None], lm[None])[0]
    px = np.abs(t[:2]) * 300.0 / 4.0
    assert px.max() < 3.0, px  # least squares would move it ~25 px


def test_too_little_evidence_keeps_the_network_place():
    joints = _body(4.0, np.random.default_rng(0))
    lm = _landmarks(joints, np.array([0.2, 0.0, 0.0]))
    few = lm.copy()
    keep = [BLAZEPOSE_NAMES.index(n) for n in ("left_hip", "right_hip")]  # 3 joints with pelvis
    few[[i for i in range(33) if i not in keep]] = np.nan
    unsure = lm.copy()
    unsure[:, 2] = 0.2
    batch = np.stack([few, unsure, np.full((33, 3), np.nan), lm])
    t = align_translation(np.repeat(joints[None], 4, 0), np.repeat(K[None], 4, 0), batch)
    np.testing.assert_array_equal(t[:3], 0.0)
    np.testing.assert_allclose(t[3], [0.2, 0.0, 0.0], atol=1e-6)
    assert AlignmentConfig().min_joints == 4


def test_a_body_is_aligned_alike_alone_and_in_a_batch():
    # a body that converges in a few steps beside one that does not: the batch stopped only when
    # every body had converged, so the first took more (tiny) steps than alone, and a body's
    # place depended on the batch it was predicted in (batch_size, a group's other crops)
    rng = np.random.default_rng(1)
    quick = _body(4.0, rng)
    lm_quick = _landmarks(quick, np.array([0.1, 0.0, 0.0]))
    lm_quick[:, :2] += rng.normal(0, 0.5, (33, 2))
    slow = _body(4.0, rng)
    lm_slow = _landmarks(slow, np.zeros(3))
    lm_slow[:, :2] = np.where(np.isnan(lm_slow[:, :2]), np.nan, rng.uniform(50, 200, (33, 2)))
    both = align_translation(
        np.stack([quick, slow]), np.stack([K, K]), np.stack([lm_quick, lm_slow])
    )
    for i, (joints, lm) in enumerate([(quick, lm_quick), (slow, lm_slow)]):
        alone = align_translation(joints[None], K[None], lm[None])[0]
        np.testing.assert_array_equal(both[i], alone)
