"""Landmark tokens in GST: they change the output, masking them gives exactly the image-only
network, the landmark-only mode, and HMR2's key names left alone."""

import dataclasses

import numpy as np
import pytest
import torch

from gst.model.landmarks import LandmarkInput
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset


def _nets(point_tokens: bool = True):
    torch.manual_seed(0)
    cfg = get_preset("tiny", landmark_tokens=True, landmark_point_tokens=point_tokens)
    groups = np.arange(300) % cfg.num_groups
    net = GSTNetwork(cfg, groups).eval()
    plain = GSTNetwork(dataclasses.replace(cfg, landmark_tokens=False), groups).eval()
    missing, unexpected = plain.load_state_dict(net.state_dict(), strict=False)
    assert not missing  # every image-path parameter comes from the landmark network
    return net, plain


def _inputs(B=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    images = torch.randn(B, 3, 128, 96, generator=g)
    px = torch.rand(B, 12, 2, generator=g) * 200 + 28
    conf = torch.rand(B, 12, 1, generator=g)
    K = torch.tensor([[600.0, 0, 140], [0, 600, 110], [0, 0, 1]]).expand(B, 3, 3)
    return images, LandmarkInput.from_pixels(torch.cat([px, conf], -1), K, 256)


def _fields(out):
    return [out.body_pose_6d, out.betas, out.cam] + [
        getattr(out.gaussians, f.name) for f in dataclasses.fields(out.gaussians)
    ]


def test_landmarks_change_pose_and_gaussians():
    net, _ = _nets()
    images, lm = _inputs()
    with torch.no_grad():
        a, b = net(images, landmarks=lm), net(images)
        c = net(images, landmarks=_inputs(seed=2)[1])
    assert (a.body_pose_6d - b.body_pose_6d).abs().max() > 1e-4
    assert (a.body_pose_6d - c.body_pose_6d).abs().max() > 1e-4  # depends on where they are
    assert (a.gaussians.colors - b.gaussians.colors).abs().max() > 1e-6


@pytest.mark.parametrize("point_tokens", [True, False])
def test_masked_landmarks_give_exactly_the_image_only_network(point_tokens):
    net, plain = _nets(point_tokens)
    images, lm = _inputs()
    with torch.no_grad():
        ref = plain(images)
        for out in (net(images), net(images, landmarks=lm.masked())):
            for x, y in zip(_fields(out), _fields(ref), strict=True):
                assert torch.equal(x, y)
        # mixed batch: the masked samples are exact, the others use their landmarks
        drop = torch.tensor([True, False, True, False])
        mixed = net(images, landmarks=lm.masked(drop))
        for x, y in zip(_fields(mixed), _fields(ref), strict=True):
            assert torch.equal(x[drop], y[drop])
        assert not torch.equal(mixed.body_pose_6d[~drop], ref.body_pose_6d[~drop])


def test_landmark_only_mode_trains_the_landmark_path():
    net, _ = _nets()
    net.train()
    _, lm = _inputs()
    lm.mask[0, :6] = False  # partly masked samples are fine
    out = net(None, with_gaussians=False, landmarks=lm)
    assert torch.isfinite(out.body_pose_6d).all()
    out.body_pose_6d.square().mean().backward()
    enc = [p.grad for p in net.landmark_encoder.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in enc)
    assert any(g.abs().sum() > 0 for g in enc)
    assert all(p.grad is None for p in net.backbone.parameters())  # no image tokens at all
    with pytest.raises(ValueError, match="at least one landmark"):
        net(None, landmarks=lm.masked(torch.tensor([True, False, False, False])))
    with pytest.raises(ValueError, match="images, landmarks or both"):
        net(None)


def test_hmr2_key_names_are_unchanged_and_plain_networks_refuse_landmarks():
    net, plain = _nets()
    new = {k for k in net.state_dict() if k not in plain.state_dict()}
    assert new and all(
        k.startswith("landmark_encoder.")
        or ".transformer.landmark_layers." in k
        or k == "smpl_head.transformer.smpl_image_gate"
        for k in new
    )
    assert set(plain.state_dict()) <= set(net.state_dict())
    images, lm = _inputs()
    with pytest.raises(ValueError, match="without landmark_tokens"):
        plain(images, landmarks=lm)


def test_landmark_input_checks_shapes_and_normalises():
    K = torch.eye(3).expand(2, 3, 3).clone()
    K[:, 0, 0] = K[:, 1, 1] = 512.0
    K[:, 0, 2] = K[:, 1, 2] = 127.5
    px = torch.tensor([[[-0.5, -0.5, 0.3], [255.5, 127.5, 1.7]]]).expand(2, 2, 3)
    inp = LandmarkInput.from_pixels(px, K, 256)
    assert torch.allclose(inp.points[0, 0], torch.tensor([-1.0, -1.0, 0.3]))
    assert torch.allclose(inp.points[0, 1], torch.tensor([1.0, 0.0, 1.0]))  # confidence clamped
    assert torch.allclose(inp.camera[0], torch.tensor([0.25, 0.0, 0.0]))
    with pytest.raises(ValueError, match="K_crop"):
        LandmarkInput.from_pixels(px, K[:1], 256)


def test_a_closed_image_gate_keeps_the_landmark_pose_and_leaves_the_rest_alone():
    """Gate 0: a crop with landmarks gets its landmark-only pose whatever the image; crops
    without landmarks and the Gaussian tokens still see the image."""
    net, plain = _nets(point_tokens=False)
    with torch.no_grad():
        net.smpl_head.transformer.smpl_image_gate.zero_()
        images, lm = _inputs()
        other = torch.randn_like(images)
        a, b = net(images, landmarks=lm), net(other, landmarks=lm)
        only = net(None, with_gaussians=False, landmarks=lm)
        assert torch.equal(a.body_pose_6d, b.body_pose_6d)
        assert torch.allclose(a.body_pose_6d, only.body_pose_6d, atol=1e-6)
        assert not torch.equal(a.gaussians.colors, b.gaussians.colors)
        drop = torch.tensor([True, False, False, True])
        mixed = net(images, landmarks=lm.masked(drop))
        ref = plain(images)
        assert torch.equal(mixed.body_pose_6d[drop], ref.body_pose_6d[drop])


def _pose(out):
    return [out.body_pose_6d, out.rotmats, out.betas, out.cam]


def test_pose_from_landmarks_skips_the_image_path_only_where_there_are_landmarks():
    """`image_for_pose=False`: samples with a usable landmark get the landmark-only mode's
    pose exactly and never reach the ViT; samples without keep the image path exactly."""
    net, _ = _nets()
    images, lm = _inputs(B=5)
    lm = lm.masked(torch.tensor([False, True, False, False, True]))  # 1 and 4: no landmarks
    calls = []
    hook = net.backbone.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    with torch.no_grad():
        fast = net(images, with_gaussians=False, landmarks=lm, image_for_pose=False)
        full = net(images, with_gaussians=False, landmarks=lm)
        alone = net(None, with_gaussians=False, landmarks=lm.rows(torch.tensor([0, 2, 3])))
        all_lm = net(
            images[[0, 2, 3]],
            with_gaussians=False,
            landmarks=lm.rows(torch.tensor([0, 2, 3])),
            image_for_pose=False,
        )  # noqa: E501
    hook.remove()
    assert calls == [2, 5]  # the fast call ran the ViT on the two crops without landmarks only
    for f, a, o in zip(_pose(fast), _pose(full), _pose(alone), strict=True):
        torch.testing.assert_close(f[[1, 4]], a[[1, 4]], rtol=0, atol=1e-6)
        torch.testing.assert_close(f[[0, 2, 3]], o, rtol=0, atol=1e-6)
    for f, o in zip(_pose(all_lm), _pose(alone), strict=True):
        torch.testing.assert_close(f, o, rtol=0, atol=0)
    with torch.no_grad():  # with Gaussians the image is needed: the flag changes nothing
        g = net(images, landmarks=lm, image_for_pose=False)
        h = net(images, landmarks=lm)
    for a, b in zip(_fields(g), _fields(h), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("gate, skips", [(0.0, True), (-0.04, True), (0.06, False), (1.0, False)])
def test_the_image_gate_decides_whether_pose_needs_the_image(gate, skips):
    from gst.model.inference import image_shapes_pose

    net, plain = _nets()
    with torch.no_grad():
        net.smpl_head.transformer.smpl_image_gate.fill_(gate)
        net.smpl_head.transformer.smpl_image_gate[0] = gate / 2  # the largest magnitude counts
    assert image_shapes_pose(net) is not skips
    assert image_shapes_pose(plain) is True  # no landmark tokens: the image is the only input
