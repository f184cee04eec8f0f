"""GST network: shapes, token count, pose independence from Gaussian tokens, HMR2 import."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from gst.model.hmr2_import import import_hmr2
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset


def hmr2_key_shapes(
    vit_dim=1280,
    depth=32,
    grid=(16, 12),
    head_dim=1024,
    head_depth=6,
    heads=8,
    dim_head=64,
    mlp=1024,
    mlp_ratio=4,
) -> dict[str, tuple]:
    """HMR2 checkpoint keys and shapes, written from the published layout (facts.md), not from
    our module names."""
    d, inner = vit_dim, heads * dim_head
    s = {
        "backbone.patch_embed.proj.weight": (d, 3, 16, 16),
        "backbone.patch_embed.proj.bias": (d,),
        "backbone.pos_embed": (1, grid[0] * grid[1] + 1, d),
        "backbone.last_norm.weight": (d,),
        "backbone.last_norm.bias": (d,),
    }
    for i in range(depth):
        b = f"backbone.blocks.{i}."
        s.update(
            {
                b + "norm1.weight": (d,),
                b + "norm1.bias": (d,),
                b + "attn.qkv.weight": (3 * d, d),
                b + "attn.qkv.bias": (3 * d,),
                b + "attn.proj.weight": (d, d),
                b + "attn.proj.bias": (d,),
                b + "norm2.weight": (d,),
                b + "norm2.bias": (d,),
                b + "mlp.fc1.weight": (mlp_ratio * d, d),
                b + "mlp.fc1.bias": (mlp_ratio * d,),
                b + "mlp.fc2.weight": (d, mlp_ratio * d),
                b + "mlp.fc2.bias": (d,),
            }
        )
    h = "smpl_head.transformer."
    s.update(
        {
            h + "to_token_embedding.weight": (head_dim, 1),
            h + "to_token_embedding.bias": (head_dim,),
            h + "pos_embedding": (1, 1, head_dim),
        }
    )
    for layer in range(head_depth):
        p = f"{h}transformer.layers.{layer}."
        for j in range(3):
            s[p + f"{j}.norm.weight"] = (head_dim,)
            s[p + f"{j}.norm.bias"] = (head_dim,)
        s.update(
            {
                p + "0.fn.to_qkv.weight": (3 * inner, head_dim),
                p + "0.fn.to_out.0.weight": (head_dim, inner),
                p + "0.fn.to_out.0.bias": (head_dim,),
                p + "1.fn.to_q.weight": (inner, head_dim),
                p + "1.fn.to_kv.weight": (2 * inner, d),
                p + "1.fn.to_out.0.weight": (head_dim, inner),
                p + "1.fn.to_out.0.bias": (head_dim,),
                p + "2.fn.net.0.weight": (mlp, head_dim),
                p + "2.fn.net.0.bias": (mlp,),
                p + "2.fn.net.3.weight": (head_dim, mlp),
                p + "2.fn.net.3.bias": (head_dim,),
            }
        )
    s.update(
        {
            "smpl_head.decpose.weight": (144, head_dim),
            "smpl_head.decpose.bias": (144,),
            "smpl_head.decshape.weight": (10, head_dim),
            "smpl_head.decshape.bias": (10,),
            "smpl_head.deccam.weight": (3, head_dim),
            "smpl_head.deccam.bias": (3,),
            "smpl_head.init_body_pose": (1, 144),
            "smpl_head.init_betas": (1, 10),
            "smpl_head.init_cam": (1, 3),
        }
    )
    return s


def groups(n_vertices=300, k=26):
    return np.arange(n_vertices) % k


def test_huge_preset_matches_hmr2_layout_exactly():
    cfg = get_preset("huge")
    with torch.device("meta"):
        net = GSTNetwork(cfg, groups(6890))
    own = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    expected = hmr2_key_shapes()
    assert {k: own.get(k) for k in expected} == expected
    extra = [k for k in own if k not in expected]
    assert extra and all(k.startswith("gaussian_head.") for k in extra)
    assert net.num_query_tokens == 5 * 26 + 1


def _tiny_net_and_hmr2_state():
    """The tiny network, HMR2's key shapes at its size, and random HMR2-style weights."""
    cfg = replace(get_preset("tiny"), num_groups=26)
    net = GSTNetwork(cfg, groups())
    shapes = hmr2_key_shapes(
        vit_dim=cfg.vit.dim,
        depth=cfg.vit.depth,
        grid=cfg.vit.grid,
        head_dim=cfg.decoder.dim,
        head_depth=cfg.decoder.depth,
        heads=cfg.decoder.heads,
        dim_head=cfg.decoder.dim_head,
        mlp=cfg.decoder.mlp_dim,
    )
    gen = torch.Generator().manual_seed(0)
    return net, shapes, {k: torch.randn(s, generator=gen) for k, s in shapes.items()}


def test_hmr2_import_maps_keys_and_reports_unmatched():
    net, shapes, state = _tiny_net_and_hmr2_state()
    state["smpl.body_pose"] = torch.zeros(1, 69)
    state["discriminator.pose.0.weight"] = torch.zeros(2, 2)
    report = import_hmr2(net, state)
    assert sorted(report.unmatched_checkpoint_keys) == [
        "discriminator.pose.0.weight",
        "smpl.body_pose",
    ]
    assert len(report.loaded) == len(shapes)
    assert all(k.startswith("gaussian_head.") for k in report.missing_model_keys)
    torch.testing.assert_close(
        net.state_dict()["backbone.blocks.1.attn.qkv.weight"],
        state["backbone.blocks.1.attn.qkv.weight"],
    )
    bad = dict(state)
    bad["smpl_head.decpose.weight"] = torch.zeros(10, 3)
    with pytest.raises(ValueError, match="shapes differ"):
        import_hmr2(net, bad)
    # a file with nothing of HMR2's (or HMR2's under another prefix) is an error, not a run
    # that silently starts from random weights
    before = {k: v.clone() for k, v in net.state_dict().items()}
    for wrong in (
        {"model.encoder.weight": torch.zeros(3, 3)},
        {f"model.{k}": v for k, v in state.items()},
    ):
        with pytest.raises(ValueError, match="backbone"):
            import_hmr2(net, wrong)
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_hmr2_weights_that_are_not_finite_are_refused_before_loading(value):
    """GST checkpoints with NaN or infinite weights are refused naming the weight; imported
    HMR2 weights were loaded as they were, and training failed at its first batch."""
    net, shapes, state = _tiny_net_and_hmr2_state()
    state["smpl_head.decpose.weight"][0, 0] = value
    state["discriminator.pose.0.weight"] = torch.full((2, 2), float("nan"))  # not imported
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with pytest.raises(
        ValueError, match=r"HMR2 import.*'smpl_head\.decpose\.weight' is not finite"
    ):
        import_hmr2(net, state)
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    state["smpl_head.decpose.weight"][0, 0] = 0.0
    assert len(import_hmr2(net, state).loaded) == len(shapes)


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    cfg = get_preset("tiny")
    return GSTNetwork(cfg, groups(400)).eval()


def test_outputs_shapes_and_unit_quaternions(tiny):
    x = torch.randn(2, 3, *tiny.cfg.image_size)
    out = tiny(x)
    assert (
        out.rotmats.shape == (2, 24, 3, 3)
        and out.betas.shape == (2, 10)
        and out.cam.shape == (2, 3)
    )
    g = out.gaussians
    assert (
        g.colors.shape == (2, 400, 3)
        and g.quats.shape == (2, 400, 4)
        and g.opacities.shape == (2, 400)
    )
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(2, 400))
    c = tiny.cfg
    assert (
        float(g.scales.detach().min()) >= c.min_scale
        and float(g.scales.detach().max()) <= c.max_scale
    )
    assert float(g.offsets.detach().abs().max()) <= c.max_offset
    eye = torch.eye(3).expand(2, 24, 3, 3)
    torch.testing.assert_close(out.rotmats @ out.rotmats.transpose(-1, -2), eye, atol=1e-5, rtol=0)


def test_smpl_output_does_not_depend_on_gaussian_tokens(tiny):
    x = torch.randn(3, 3, *tiny.cfg.image_size)
    full = tiny(x, with_gaussians=True)
    pose_only = tiny(x, with_gaussians=False)
    assert pose_only.gaussians is None
    torch.testing.assert_close(full.body_pose_6d, pose_only.body_pose_6d, rtol=0, atol=0)
    with torch.no_grad():
        tiny.gaussian_head.tokens.add_(
            1.0
        )  # changing the Gaussian tokens leaves the pose untouched
        again = tiny(x, with_gaussians=True)
        tiny.gaussian_head.tokens.sub_(1.0)
    torch.testing.assert_close(again.body_pose_6d, full.body_pose_6d, rtol=0, atol=0)


def test_wrong_input_shape_is_a_clear_error(tiny):
    with pytest.raises(ValueError, match="ViT input must be"):
        tiny(torch.randn(1, 3, 64, 64))


def test_crop_inputs_are_checked_before_the_network_runs(tiny):
    """One K per crop, finite, positive focal lengths (a single K was broadcast to every crop;
    fx = 0 surfaced as a NaN in the body model); float crops in [0, 1] (0-255 floats were read
    as overexposed); BGR -> RGB views with negative strides are taken (torch refused them)."""
    from gst.model.inference import predict_bodies
    from gst.model.preprocess import check_intrinsics, to_float_images

    rgb = np.random.default_rng(0).integers(0, 256, (4, 32, 32, 3), dtype=np.uint8)
    K = np.tile(np.array([[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]]), (4, 1, 1))
    check_intrinsics(K, 4)
    for bad, what in ((K[:1], "one per crop"), (K * np.nan, "not an intrinsic"), (K * 0, "fx")):
        with pytest.raises(ValueError, match=what):
            check_intrinsics(bad, 4)
    with pytest.raises(ValueError, match="one per crop"):
        predict_bodies(tiny, None, None, rgb, torch.as_tensor(K[:1]), tiny.cfg.image_size)
    bgr_view = rgb[..., ::-1]
    torch.testing.assert_close(
        to_float_images(bgr_view), to_float_images(np.ascontiguousarray(bgr_view))
    )
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        to_float_images(rgb.astype(np.float32))


def test_an_empty_batch_runs(tiny):
    """A batch of 0 crops failed in the attention's head split (view(b, n, heads, -1) cannot
    size a dimension of an empty tensor)."""
    out = tiny(torch.randn(0, 3, *tiny.cfg.image_size))
    assert out.rotmats.shape == (0, 24, 3, 3) and out.gaussians.quats.shape == (0, 400, 4)


@pytest.mark.parametrize(
    "content, expected",
    [
        (b"", "cannot be read as a torch checkpoint (EOFError"),
        (b"hello\n", "cannot be read as a torch checkpoint"),
        ("cut", "is the file whole"),
    ],
)
def test_unreadable_hmr2_files_are_named_without_unsafe_advice(tmp_path, content, expected):
    """An empty or cut download gave a bare EOFError, or advice to unpickle it with
    weights_only=False."""
    from gst.model.hmr2_import import read_checkpoint_state

    path = tmp_path / "hmr2.ckpt"
    if content == "cut":
        torch.save({"state_dict": {"w": torch.ones(1000)}}, path)
        path.write_bytes(path.read_bytes()[:2000])
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError) as err:
        read_checkpoint_state(path)
    assert str(path) in str(err.value) and expected in str(err.value)
    assert "weights_only=False" not in str(err.value)


class _Payload:
    """Pickles as a call of os.getcwd: what a malicious checkpoint would run."""

    def __reduce__(self):
        import os

        return (os.getcwd, ())


def test_a_refused_pickle_names_what_was_refused_and_gives_no_unsafe_advice(tmp_path):
    """torch's first line, cut at 200 characters, ended advising weights_only=False and lost
    the refused object; HMR2's reader advised a weights_only=False re-save for a .npy too."""
    from gst.model.checkpoint import load_checkpoint
    from gst.model.hmr2_import import read_checkpoint_state

    evil = tmp_path / "evil.pt"
    torch.save({"format": "x", "payload": _Payload()}, evil)
    with pytest.raises(ValueError) as err:
        load_checkpoint(evil)
    assert "GLOBAL posix.getcwd" in str(err.value) and "weights_only" not in str(err.value)
    npy = tmp_path / "weights.npy"
    np.save(npy, np.ones(3))
    with pytest.raises(ValueError) as err:
        read_checkpoint_state(npy)
    assert "weights_only=False" not in str(err.value)


def test_float_crops_outside_0_1_and_non_image_types_are_refused():
    """Crops scaled to [-1, 1] were normalised again (joints 26 cm off on the demo); a bool
    mask passed as crops was taken for an image."""
    from gst.model.preprocess import to_float_images

    x = np.random.default_rng(0).uniform(-1, 1, (2, 8, 8, 3)).astype(np.float32)
    with pytest.raises(ValueError, match="minimum of .*\\(x \\+ 1\\) / 2"):
        to_float_images(x)
    with pytest.raises(ValueError, match="uint8 .* or float in \\[0, 1\\], got bool"):
        to_float_images(np.zeros((2, 8, 8, 3), bool))
    assert to_float_images((x + 1) / 2).shape == (2, 3, 8, 8)
