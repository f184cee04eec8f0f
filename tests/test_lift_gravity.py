"""The camera's up direction as an input of the landmark path (GSTConfig.landmark_gravity): it
changes the pose when known, a zero row means "not known", networks without it ignore it,
old checkpoints load without it, and tracking passes it only for calibrated cameras."""

import dataclasses

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.lift.pretrain import simulated_up
from gst.model.checkpoint import config_from_dict, config_to_dict
from gst.model.landmarks import UNCALIBRATED_EVERY, LandmarkInput, camera_up
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset


def _net(gravity: bool) -> GSTNetwork:
    torch.manual_seed(0)
    cfg = get_preset("tiny", landmark_tokens=True, num_landmarks=33, landmark_gravity=gravity)
    return GSTNetwork(cfg, np.arange(300) % cfg.num_groups).eval()


def _landmarks(B=3, up=None):
    g = torch.Generator().manual_seed(3)
    px = torch.rand(B, 33, 2, generator=g) * 200 + 28
    lm = torch.cat([px, torch.rand(B, 33, 1, generator=g) * 0.5 + 0.5], -1)
    K = torch.tensor([[600.0, 0, 128], [0, 600, 128], [0, 0, 1]]).expand(B, 3, 3)
    return LandmarkInput.from_pixels(lm, K, 256, up=up)


def _pose(net, inp):
    with torch.no_grad():
        return net(None, with_gaussians=False, landmarks=inp).body_pose_6d


def _trained_gravity_net() -> GSTNetwork:
    """A gravity network whose up-vector weights are not zero-ish (they are at init too, but
    make the dependence unmistakable)."""
    net = _net(True)
    with torch.no_grad():
        net.landmark_encoder.lift[0].weight[:, -4:].normal_(0, 1.0)
    return net


def test_a_known_up_changes_the_pose_and_a_zero_row_means_unknown():
    net = _trained_gravity_net()
    level = torch.tensor([[0.0, -1.0, 0.0]]).repeat(3, 1)  # camera y points down: level camera
    tilted = torch.tensor([[0.0, -0.8, -0.6]]).repeat(3, 1)
    a, b = _pose(net, _landmarks(up=level)), _pose(net, _landmarks(up=tilted))
    assert (a - b).abs().max() > 1e-3
    unknown, none = _pose(net, _landmarks(up=torch.zeros(3, 3))), _pose(net, _landmarks())
    assert torch.equal(unknown, none)
    assert (unknown - a).abs().max() > 1e-3
    nan = _pose(net, _landmarks(up=torch.full((3, 3), float("nan"))))
    assert torch.equal(nan, none)  # a non-finite row is "not known", not NaN poses
    scaled = _pose(net, _landmarks(up=3.0 * level))
    assert torch.allclose(scaled, a, atol=1e-6)  # only the direction counts


def test_networks_without_gravity_ignore_the_up_vector():
    net = _net(False)
    up = torch.tensor([[0.0, -0.8, -0.6]]).repeat(3, 1)
    assert torch.equal(_pose(net, _landmarks(up=up)), _pose(net, _landmarks()))


def test_up_must_have_one_row_per_sample():
    with pytest.raises(ValueError, match=r"up must be \(3, 3\)"):
        _landmarks(up=torch.zeros(2, 3))


def test_checkpoints_written_before_gravity_load_without_it():
    cfg = get_preset("tiny", landmark_tokens=True, landmark_gravity=True)
    d = config_to_dict(cfg)
    assert config_from_dict(d).landmark_gravity is True
    del d["landmark_gravity"]
    assert config_from_dict(d).landmark_gravity is False
    assert dataclasses.replace(cfg, landmark_gravity=False) == config_from_dict(d)


@settings(max_examples=30, deadline=None)
@given(
    st.floats(-np.pi, np.pi), st.floats(-1.4, 1.4), st.floats(-np.pi, np.pi),
    st.sampled_from([(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, 0.0, 2.0)]),
)  # fmt: skip
def test_camera_up_is_the_rotated_unit_world_up(yaw, pitch, roll, world_up):
    import cv2

    R = cv2.Rodrigues(np.array([pitch, yaw, roll]))[0]
    up = camera_up(torch.as_tensor(R, dtype=torch.float64)[None], world_up)[0].numpy()
    w = np.asarray(world_up) / np.linalg.norm(world_up)
    np.testing.assert_allclose(up, R @ w, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(up), 1.0, atol=1e-12)


def test_simulated_batches_hide_the_up_of_every_fifth_sample():
    class B:
        R = torch.eye(3).repeat(12, 1, 1)

    up = simulated_up(B())
    hidden = (up == 0).all(-1)
    assert hidden.tolist() == [(k + 1) % UNCALIBRATED_EVERY == 0 for k in range(12)]
    assert torch.allclose(up[~hidden], torch.tensor([0.0, 0.0, 1.0]))
