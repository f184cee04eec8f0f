"""Reprojection feedback (gst.model.refine): the markers it projects are the body model's
markers seen through OpenCV's projection, a fresh refiner passes the head's answer through,
samples without landmarks keep the head's output exactly, a checkpoint carries the skeleton,
and training it pulls the body onto the landmarks."""

import dataclasses

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body import load_body_model
from gst.body.markers import BLAZEPOSE_NAMES, MarkerModel
from gst.body.rotations import rot6d_to_matrix
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint, save_checkpoint
from gst.model.landmarks import LandmarkInput
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset
from gst.model.refine import ReprojectionRefiner
from gst.train.recipe import build_network

CROP = 256


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


def _landmarks(B, seed=1, n=33):
    g = torch.Generator().manual_seed(seed)
    px = torch.rand(B, n, 2, generator=g) * 160 + 48
    conf = torch.rand(B, n, 1, generator=g) * 0.5 + 0.5
    K = torch.tensor([[600.0, 0, 140], [0, 600, 110], [0, 0, 1]]).expand(B, 3, 3)
    return torch.cat([px, conf], -1), K


def _pose(B, seed=0, nb=10):
    g = torch.Generator().manual_seed(seed)
    pose6d = torch.eye(3)[:, :2].T.reshape(1, 1, 6).repeat(B, 24, 1)
    pose6d = pose6d + 0.3 * torch.randn(B, 24, 6, generator=g)
    pose6d[:, 0] = torch.tensor([1.0, 0, 0, 0, -1, 0])  # upright in an OpenCV camera
    betas = 0.5 * torch.randn(B, nb, generator=g)
    cam = torch.tensor([[0.9, 0.0, 0.0]]) + 0.05 * torch.randn(B, 3, generator=g)
    return pose6d, betas, cam


@settings(max_examples=12, deadline=None)
@given(
    f=st.floats(300, 1500),
    cx=st.floats(60, 200),
    cy=st.floats(60, 200),
    seed=st.integers(0, 1000),
)
def test_projected_markers_are_the_body_models_markers_through_opencv(body, f, cx, cy, seed):
    refiner = ReprojectionRefiner(33, 10, 1)
    refiner.set_body(body)
    pose6d, betas, cam = _pose(2, seed)
    K = torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=torch.float32).expand(2, 3, 3)
    lm, _ = _landmarks(2)
    camera = LandmarkInput.from_pixels(lm, K, CROP).camera
    with torch.no_grad():
        got = refiner.project_markers(pose6d, betas, cam, camera).double().numpy()
    # reference: the body model's full forward, the marker table on it, OpenCV's projection
    markers = MarkerModel.load()
    R = rot6d_to_matrix(pose6d)
    tz = 2 * f / (CROP * cam[:, 0])
    transl = torch.stack([cam[:, 1], cam[:, 2], tz], -1)
    with torch.no_grad():
        out = body(betas, R[:, 1:], R[:, 0], transl, vertex_ids=markers.vertex_ids,
                   return_transforms=True)  # fmt: skip
        xyz = markers.positions(out).double().numpy()
    order = [list(markers.names).index(n) for n in BLAZEPOSE_NAMES]
    for b in range(2):
        px, _ = cv2.projectPoints(
            xyz[b, order], np.zeros(3), np.zeros(3), K[b].double().numpy(), None
        )
        ref = (px[:, 0] + 0.5) / CROP * 2 - 1
        np.testing.assert_allclose(got[b], ref, atol=2e-4)


def test_a_fresh_refiner_passes_the_heads_answer_through(body):
    torch.manual_seed(0)
    cfg = get_preset("tiny", landmark_tokens=True, num_landmarks=33, landmark_refine=2)
    net, _, groups = build_network(cfg, body)
    plain = GSTNetwork(dataclasses.replace(cfg, landmark_refine=0), groups)
    missing, unexpected = plain.load_state_dict(net.state_dict(), strict=False)
    assert not missing and all(k.startswith("refiner.") for k in unexpected)
    lm, K = _landmarks(3)
    inp = LandmarkInput.from_pixels(lm, K, CROP)
    with torch.no_grad():
        a = net.eval()(None, with_gaussians=False, landmarks=inp)
        b = plain.eval()(None, with_gaussians=False, landmarks=inp)
    assert torch.equal(a.body_pose_6d, b.body_pose_6d) and torch.equal(a.cam, b.cam)


def _trained_refiner_net(body):
    torch.manual_seed(0)
    cfg = get_preset("tiny", landmark_tokens=True, num_landmarks=33, landmark_refine=2)
    net, ids, groups = build_network(cfg, body)
    with torch.no_grad():  # as if trained: the corrections are not zero
        net.refiner.out.weight.normal_(0, 0.01)
    return net.eval(), ids, groups


def test_samples_without_landmarks_keep_the_heads_output_exactly(body):
    net, _, groups = _trained_refiner_net(body)
    plain = GSTNetwork(dataclasses.replace(net.cfg, landmark_refine=0), groups)
    plain.load_state_dict(net.state_dict(), strict=False)
    plain.eval()
    images = torch.randn(4, 3, 128, 96, generator=torch.Generator().manual_seed(3))
    lm, K = _landmarks(4)
    drop = torch.tensor([True, False, True, False])
    inp = LandmarkInput.from_pixels(lm, K, CROP).masked(drop)
    with torch.no_grad():
        mixed = net(images, with_gaussians=False, landmarks=inp)
        head = plain(images, with_gaussians=False, landmarks=inp)
    for name in ("body_pose_6d", "betas", "cam"):
        x, y = getattr(mixed, name), getattr(head, name)
        assert torch.equal(x[drop], y[drop]), name
        assert not torch.equal(x[~drop], y[~drop]), name


def test_a_checkpoint_carries_the_skeleton_and_a_refiner_without_one_refuses(body, tmp_path):
    net, ids, groups = _trained_refiner_net(body)
    save_checkpoint(tmp_path / "n.pt", net, "anny", ids, groups)
    back = network_from_checkpoint(load_checkpoint(tmp_path / "n.pt")).eval()
    lm, K = _landmarks(2)
    inp = LandmarkInput.from_pixels(lm, K, CROP)
    with torch.no_grad():
        a = net(None, with_gaussians=False, landmarks=inp)
        b = back(None, with_gaussians=False, landmarks=inp)
    assert torch.equal(a.body_pose_6d, b.body_pose_6d)
    bare = GSTNetwork(net.cfg, groups)  # built without the body model
    with pytest.raises(RuntimeError, match="has no body"):
        bare(None, with_gaussians=False, landmarks=inp)


def test_the_limb_set_and_a_body_outside_the_smpl_layout():
    refiner = ReprojectionRefiner(12, 10, 1)
    assert refiner.marker_offset.shape == (12, 3)
    with pytest.raises(ValueError, match="no landmark set of 20"):
        ReprojectionRefiner(20, 10, 1)
    with pytest.raises(ValueError, match="iterations"):
        ReprojectionRefiner(33, 10, 0)


def test_training_the_refiner_pulls_the_markers_onto_the_landmarks(body):
    """The landmarks are the projection of a known body; the refiner alone is trained to
    reduce the reprojection error of the head's (wrong) body: the error must fall."""
    refiner = ReprojectionRefiner(33, 10, 2, width=128)
    refiner.set_body(body)
    B = 16
    K = torch.tensor([[500.0, 0, 127.5], [0, 500, 127.5], [0, 0, 1]]).expand(B, 3, 3)
    camera = LandmarkInput.from_pixels(torch.zeros(B, 33, 3), K, CROP).camera
    truth = _pose(B, seed=5)
    with torch.no_grad():
        xy = refiner.project_markers(*truth, camera)
    px = (xy + 1) / 2 * CROP - 0.5
    inp = LandmarkInput.from_pixels(torch.cat([px, torch.ones(B, 33, 1)], -1), K, CROP)
    start = _pose(B, seed=6)

    def error():
        p, b, c = refiner(*start, inp)
        return (refiner.project_markers(p, b, c, camera) - inp.points[..., :2]).norm(dim=-1).mean()

    with torch.no_grad():
        before = float(error())
    opt = torch.optim.Adam(refiner.parameters(), lr=1e-3)
    for _ in range(60):
        opt.zero_grad()
        loss = error()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = float(error())
    assert after < 0.7 * before, (before, after)


def test_the_tracks_metadata_names_the_rounds(body, tmp_path):
    from gst.track.scene import model_provenance

    net, ids, groups = _trained_refiner_net(body)
    save_checkpoint(tmp_path / "n.pt", net, "anny", ids, groups)
    assert model_provenance(tmp_path / "n.pt", "gst-tiny", "demo").reprojection_feedback == 2
    plain, ids, groups = build_network(get_preset("tiny"), body)
    save_checkpoint(tmp_path / "p.pt", plain, "anny", ids, groups)
    assert model_provenance(tmp_path / "p.pt", "gst-tiny", "demo").reprojection_feedback == 0
    # the weights are named by their digest: the two networks' tracks have different settings
    # (a retrained models/gst.pt kept the old tracks of a library caller's tracks folder)
    a, b = (model_provenance(tmp_path / f, "gst-tiny", "demo") for f in ("n.pt", "p.pt"))
    assert a.checkpoint == b.checkpoint and a.checkpoint_sha256 != b.checkpoint_sha256
    assert a.to_dict() != {**b.to_dict(), "reprojection_feedback": 2}


@pytest.mark.parametrize("gravity", [False, True])
def test_the_up_direction_is_read_only_by_a_gravity_aware_refiner(body, gravity):
    torch.manual_seed(0)
    refiner = ReprojectionRefiner(33, 10, 1, gravity=gravity)
    refiner.set_body(body)
    with torch.no_grad():
        refiner.out.weight.normal_(0, 0.01)
    lm, K = _landmarks(2)
    up = torch.tensor([[0.0, -1.0, 0.0], [0.0, -0.8, 0.6]])
    pose = _pose(2)
    with torch.no_grad():
        a = refiner(*pose, LandmarkInput.from_pixels(lm, K, CROP, up=up))[0]
        b = refiner(*pose, LandmarkInput.from_pixels(lm, K, CROP))[0]
    assert torch.equal(a, b) != gravity


def test_a_masked_landmark_given_as_nan_changes_nothing(body):
    """A landmark masked out but given as NaN (`from_pixels(..., mask=...)` or a LandmarkInput
    built directly): the encoder zeroed it, the refiner multiplied it by 0, and the whole
    sample's pose and camera came out NaN. Now the same as the landmark given as 0."""
    net, _, _ = _trained_refiner_net(body)
    images = torch.randn(2, 3, 128, 96, generator=torch.Generator().manual_seed(3))
    lm, K = _landmarks(2)
    mask = torch.ones(2, 33, dtype=torch.bool)
    mask[0, 5] = False
    nan, zero = lm.clone(), lm.clone()
    nan[0, 5], zero[0, 5] = float("nan"), 0.0
    with torch.no_grad():
        a = net(
            images,
            with_gaussians=False,
            landmarks=LandmarkInput.from_pixels(nan, K, CROP, mask=mask),
        )
        b = net(
            images,
            with_gaussians=False,
            landmarks=LandmarkInput.from_pixels(zero, K, CROP, mask=mask),
        )
    for name in ("body_pose_6d", "betas", "cam"):
        assert torch.isfinite(getattr(a, name)).all(), name
        assert torch.equal(getattr(a, name), getattr(b, name)), name
