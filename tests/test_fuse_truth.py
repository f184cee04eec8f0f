"""Fused bodies scored against the synthetic truth (gst.fuse.evaluate): a truth person the fusion
missed is counted, so that dropping a hard person does not read as better fusion."""

from types import SimpleNamespace

import numpy as np

from gst.fuse.evaluate import compare_with_truth, visible_person_frames
from gst.fuse.fit import PersonFit

T = 10


def _fit(pid: int, joints: np.ndarray) -> PersonFit:
    n = len(joints)
    return PersonFit(
        person_id=pid,
        frames=np.arange(n),
        betas=np.zeros(10),
        global_orient=np.zeros((n, 3)),
        body_pose=np.zeros((n, 23, 3)),
        transl=np.zeros((n, 3)),
        joints=joints,
        markers=np.zeros((n, 0, 3)),
        reprojection=np.zeros((n, 1, 0)),
        observed=np.ones(n, bool),
        static=np.zeros(n, bool),
        single_view=False,
        sigma_px=1.0,
    )


def _truth():
    rng = np.random.default_rng(0)
    people = {1: rng.normal(size=(24, 3)) * 0.2, 2: rng.normal(size=(24, 3)) * 0.2 + (3, 0, 0)}
    frame, pid, joints = [], [], []
    for f in range(T):
        for p, J in people.items():
            frame.append(f)
            pid.append(p)
            joints.append(J)
    truth = SimpleNamespace(
        frame=np.array(frame),
        person_id=np.array(pid),
        joints_world=np.array(joints),
        joint_names=[f"j{i}" for i in range(24)],
    )
    return truth, people


def test_a_truth_person_no_fused_body_stands_for_is_counted_missed():
    truth, people = _truth()
    views = SimpleNamespace(  # person 2 is hidden in frames 0-1 (only 20 % of the joints seen)
        frame=truth.frame,
        person_id=truth.person_id,
        camera=np.array(["a"] * len(truth.frame), dtype=object),
        visible=np.array([[k < (5 if p == 2 and f < 2 else 24) for k in range(24)]
                          for f, p in zip(truth.frame, truth.person_id, strict=True)]),
    )  # fmt: skip
    expected = visible_person_frames(views, range(T))
    assert len(expected) == 2 * T - 2
    near = _fit(1, np.repeat(people[1][None] + 0.02, T, axis=0))
    far = _fit(2, np.repeat(people[2][None] + 0.15, T, axis=0))
    both = compare_with_truth([near, far], truth, expected=expected)
    one = compare_with_truth([near], truth, expected=expected)
    assert (both.truth_missed, one.truth_missed) == (0, T - 2)
    assert one.truth_expected == both.truth_expected == 2 * T - 2
    assert one.mpjpe_mm < both.mpjpe_mm  # why the errors alone mislead
    # frames outside those the extraction considered are not expected
    assert visible_person_frames(views, range(0, T, 2)) <= expected
    assert len(visible_person_frames(views, range(0, T, 2))) == T - 1
    assert visible_person_frames(views, range(T), cameras=["b"]) == set()  # not the store's
    none = compare_with_truth([], truth, expected=expected)
    assert none.truth_missed == 2 * T - 2 and none.matched == 0
