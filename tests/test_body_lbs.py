"""Our LBS against smplx's lbs() on a generated model in the official SMPL layout; input checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from smplx.lbs import lbs as smplx_lbs

from gst.body import BodyModel, BodyModelData, load_body_model
from gst.body.random_model import random_body_data
from gst.body.rotations import axis_angle_to_matrix
from gst.body.smpl_file import load_smpl_file
from tests.body_fixtures import write_official_npz, write_official_pkl


@pytest.fixture(scope="module")
def small_data() -> BodyModelData:
    return random_body_data(num_vertices=900, num_betas=10, seed=3)


def _random_inputs(B: int, nb: int, dtype=torch.float64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    betas = torch.randn(B, nb, generator=g, dtype=dtype)
    pose = 0.6 * torch.randn(B, 23, 3, generator=g, dtype=dtype)
    orient = 1.5 * torch.randn(B, 3, generator=g, dtype=dtype)
    transl = torch.randn(B, 3, generator=g, dtype=dtype)
    return betas, pose, orient, transl


def _smplx_reference(data: BodyModelData, betas, pose, orient, dtype=torch.float64):
    """smplx's lbs on the raw arrays. Rotations come from scipy (smplx's own Rodrigues adds
    1e-8 to the rotation vectors, which alone moves vertices by ~1e-8)."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
    full_pose = torch.cat([orient[:, None], pose], dim=1).reshape(-1, 3).numpy()
    rotmats = t(Rotation.from_rotvec(full_pose).as_matrix()).reshape(len(pose), 24, 3, 3)
    return smplx_lbs(
        betas,
        rotmats,
        t(data.v_template),
        t(data.shapedirs),
        t(data.posedirs),
        t(data.dense_J_regressor()),
        torch.as_tensor(np.asarray(data.parents)),
        t(data.weights),
        pose2rot=False,
    )


@pytest.mark.parametrize("fmt, protocol", [("pkl", 2), ("pkl", 1), ("npz", None)])
def test_lbs_matches_smplx_on_official_file(tmp_path, small_data, fmt, protocol):
    """Write the model in the official layout (chumpy arrays and a sparse regressor in the .pkl),
    load it back through our safe loader, and compare with smplx on the file's own arrays."""
    path = tmp_path / f"SMPL_NEUTRAL.{fmt}"
    if fmt == "pkl":
        write_official_pkl(small_data, path, protocol=protocol)
    else:
        write_official_npz(small_data, path)
    loaded = load_smpl_file(tmp_path)  # a folder: finds SMPL_NEUTRAL.*
    for field in ("v_template", "shapedirs", "weights", "posedirs", "faces", "parents"):
        np.testing.assert_array_equal(
            np.asarray(getattr(loaded, field)), np.asarray(getattr(small_data, field))
        )
    np.testing.assert_array_equal(loaded.dense_J_regressor(), small_data.dense_J_regressor())

    betas, pose, orient, _ = _random_inputs(6, 10)
    ref_v, ref_j = _smplx_reference(loaded, betas, pose, orient)
    for dtype, tol in ((torch.float64, 1e-10), (torch.float32, 1e-5)):
        body = BodyModel(loaded, dtype=dtype)
        out = body(betas, pose, orient)
        assert out.vertices.dtype == dtype
        assert (out.vertices.double() - ref_v).abs().max() < tol
        assert (out.joints.double() - ref_j).abs().max() < tol


def test_rotmat_axis_angle_and_flat_inputs_agree(small_data):
    body = BodyModel(small_data, dtype=torch.float64)
    betas, pose, orient, transl = _random_inputs(3, 10, seed=1)
    a = body(betas, pose, orient, transl)
    b = body(betas, axis_angle_to_matrix(pose), axis_angle_to_matrix(orient), transl)
    c = body(betas, pose.reshape(3, 69), orient[:, None], transl)
    for other in (b, c):
        torch.testing.assert_close(other.vertices, a.vertices, rtol=0, atol=1e-12)
        torch.testing.assert_close(other.joints, a.joints, rtol=0, atol=1e-12)


def test_transforms_subsets_and_translation(small_data):
    body = BodyModel(small_data, dtype=torch.float64)
    betas, pose, orient, transl = _random_inputs(4, 10, seed=2)
    ids = torch.tensor([0, 5, 17, 400, 899])
    full = body(betas, pose, orient, transl, return_transforms=True)
    sub = body(betas, pose, orient, transl, vertex_ids=ids, return_transforms=True)
    torch.testing.assert_close(sub.vertices, full.vertices[:, ids], rtol=0, atol=1e-12)
    torch.testing.assert_close(
        sub.vertex_transforms, full.vertex_transforms[:, ids], rtol=0, atol=1e-12
    )
    torch.testing.assert_close(sub.joints, full.joints, rtol=0, atol=0)
    assert full.joint_transforms.shape == (4, 24, 4, 4) and full.vertex_transforms.shape == (
        4,
        900,
        4,
        4,
    )

    # The vertex transform maps the rest vertex (with pose correctives) to the posed vertex.
    eye = torch.eye(3, dtype=torch.float64)
    rot = axis_angle_to_matrix(torch.cat([orient[:, None], pose], 1))
    rest = body.rest_vertices(betas) + ((rot[:, 1:] - eye).reshape(4, -1) @ body.posedirs).reshape(
        4, -1, 3
    )
    moved = (full.vertex_transforms[..., :3, :3] @ rest[..., None])[
        ..., 0
    ] + full.vertex_transforms[..., :3, 3]
    torch.testing.assert_close(moved, full.vertices, rtol=0, atol=1e-12)
    # A joint transform maps that joint's rest position to its posed position.
    rest_j = body.rest_joints(betas)
    moved_j = (full.joint_transforms[..., :3, :3] @ rest_j[..., None])[
        ..., 0
    ] + full.joint_transforms[..., :3, 3]
    torch.testing.assert_close(moved_j, full.joints, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        full.vertex_transforms[..., 3, :],
        torch.tensor([0.0, 0, 0, 1], dtype=torch.float64).expand(4, 900, 4),
    )
    # Translation shifts everything rigidly.
    plain = body(betas, pose, orient)
    torch.testing.assert_close(full.vertices, plain.vertices + transl[:, None], rtol=0, atol=1e-12)
    torch.testing.assert_close(full.joints, plain.joints + transl[:, None], rtol=0, atol=1e-12)


def test_rest_pose_reproduces_template(small_data):
    body = BodyModel(small_data, dtype=torch.float64)
    out = body(
        torch.zeros(1, 10, dtype=torch.float64),
        torch.zeros(1, 69),
        torch.zeros(1, 3),
        return_transforms=True,
    )
    np.testing.assert_allclose(out.vertices[0].numpy(), small_data.v_template, atol=1e-12)
    np.testing.assert_allclose(
        out.joints[0].numpy(), small_data.dense_J_regressor() @ small_data.v_template, atol=1e-12
    )
    torch.testing.assert_close(
        out.joint_transforms, torch.eye(4, dtype=torch.float64).expand(1, 24, 4, 4)
    )


def test_fewer_betas_and_broadcast(small_data):
    body = BodyModel(small_data, dtype=torch.float64)
    betas, pose, orient, _ = _random_inputs(3, 10, seed=4)
    padded = torch.cat([betas[:, :4], torch.zeros(3, 6, dtype=torch.float64)], 1)
    torch.testing.assert_close(
        body(betas[:, :4], pose, orient).vertices, body(padded, pose, orient).vertices
    )
    one = body(betas[:1], pose, orient)  # (1, nb) betas broadcast over the batch
    torch.testing.assert_close(one.vertices, body(betas[:1].expand(3, -1), pose, orient).vertices)
    assert body(None, pose, orient).vertices.shape == (3, 900, 3)


def test_gradients_match_finite_differences():
    data = random_body_data(num_vertices=400, num_betas=4, seed=5)
    body = BodyModel(data, dtype=torch.float64)
    betas, pose, orient, transl = _random_inputs(1, 4, seed=6)
    ids = torch.arange(0, 400, 37)
    g = torch.Generator().manual_seed(7)
    w_v = torch.randn(1, len(ids), 3, generator=g, dtype=torch.float64)
    w_j = torch.randn(1, 24, 3, generator=g, dtype=torch.float64)
    w_t = torch.randn(1, len(ids), 4, 4, generator=g, dtype=torch.float64)

    def f(b, p, o, t):  # random projections keep the Jacobian small
        out = body(b, p, o, t, vertex_ids=ids, return_transforms=True)
        return torch.stack(
            [
                (out.vertices * w_v).sum(),
                (out.joints * w_j).sum(),
                (out.vertex_transforms * w_t).sum(),
            ]
        )

    inputs = tuple(x.clone().requires_grad_(True) for x in (betas, pose, orient, transl))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, fast_mode=True)


def _bad_call(body, **override):
    betas, pose, orient, transl = _random_inputs(2, 10, dtype=torch.float32)
    args = {"betas": betas, "body_pose": pose, "global_orient": orient, "transl": transl}
    args.update(override)
    return body(**args)


@pytest.mark.parametrize(
    "name, value, message",
    [
        (
            "body_pose",
            torch.zeros(2, 24, 3),
            r"body_pose must have shape \(B, 23, 3, 3\).*got \(2, 24, 3\)",
        ),
        ("body_pose", torch.zeros(2, 23, 3, 2), r"body_pose must have shape"),
        ("global_orient", torch.zeros(2, 4), r"global_orient must have shape \(B, 3, 3\)"),
        (
            "global_orient",
            torch.zeros(3, 3, 3),
            r"global_orient has batch 3 but body_pose has batch 2",
        ),
        ("betas", torch.zeros(2, 11), r"betas must have shape \(B, nb\).*nb <= 10.*got \(2, 11\)"),
        ("betas", torch.zeros(10), r"betas must have shape"),
        ("transl", torch.zeros(2, 2), r"transl must have shape \(2, 3\)"),
        (
            "body_pose",
            torch.zeros(2, 23, 3, dtype=torch.int64),
            r"body_pose must be a floating-point tensor",
        ),
        ("vertex_ids", torch.tensor([0, 900]), r"vertex_ids must lie in \[0, 900\)"),
    ],
)
def test_wrong_shapes_name_the_argument(small_data, name, value, message):
    body = BodyModel(small_data)
    with pytest.raises(ValueError, match=message):
        _bad_call(body, **{name: value})


@pytest.mark.parametrize("name", ["body_pose", "global_orient", "betas", "transl"])
def test_nan_inputs_raise(small_data, name):
    body = BodyModel(small_data)
    betas, pose, orient, transl = _random_inputs(2, 10, dtype=torch.float32)
    args = {"betas": betas, "body_pose": pose, "global_orient": orient, "transl": transl}
    args[name] = args[name].clone()
    args[name].view(-1)[-1] = float("nan")
    with pytest.raises(ValueError, match=rf"{name} contains NaN or Inf \(batch items \[1\]\)"):
        body(**args)


def test_model_attributes_and_dtype_switch(small_data):
    body = BodyModel(small_data)
    assert (body.num_vertices, body.num_joints, body.num_betas) == (900, 24, 10)
    assert isinstance(body.faces, np.ndarray) and body.faces.shape[1] == 3
    assert body.parents[0] == -1 and len(body.joint_names) == 24 and body.joint_names[0] == "pelvis"
    assert body.part_labels.shape == (900,) and body.part_names is not None
    body64 = body.to(torch.float64)
    out = body64(*_random_inputs(1, 10, dtype=torch.float32)[:3])
    assert out.vertices.dtype == torch.float64


def test_data_npz_round_trip_and_load_body_model(tmp_path, small_data):
    path = small_data.save_npz(tmp_path / "body.npz")
    back = BodyModelData.load_npz(path)
    np.testing.assert_array_equal(back.shapedirs, small_data.shapedirs)
    np.testing.assert_array_equal(back.dense_J_regressor(), small_data.dense_J_regressor())
    assert back.joint_names == small_data.joint_names and back.part_names == small_data.part_names
    assert not list(tmp_path.glob("*.tmp"))
    body = load_body_model(str(path), dtype=torch.float64)
    assert body.num_vertices == 900 and body.dtype == torch.float64
    pkl = write_official_pkl(small_data, tmp_path / "mine.pkl")
    assert load_body_model(str(pkl)).num_vertices == 900


def test_invalid_data_names_the_field(small_data):
    bad = small_data.replace(weights=np.asarray(small_data.weights)[:, :23])
    with pytest.raises(ValueError, match=r"weights has shape \(900, 23\)|shapedirs|J_regressor"):
        BodyModel(bad)
    bad = small_data.replace(parents=np.array([-1] + [5] * 23))
    with pytest.raises(ValueError, match="parents"):
        BodyModel(bad)


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 cut short"])
def test_a_damaged_body_file_is_a_value_error_naming_it(tmp_path, small_data, content):
    """A cut-short or empty .npz raised BadZipFile / EOFError, which the Anny cache's
    rebuild-on-damage path did not catch (it catches ValueError)."""
    path = tmp_path / "body.npz"
    small_data.save_npz(path)
    path.write_bytes(content or path.read_bytes()[:300])
    with pytest.raises(ValueError, match=r"body\.npz: not a readable npz body file"):
        BodyModelData.load_npz(path)


def test_a_body_file_with_a_damaged_member_is_a_value_error_naming_it(tmp_path, small_data):
    """A flipped byte inside a member (bad CRC) raised BadZipFile on reading the array, past
    the guarded open, so the Anny cache did not rebuild its damaged file."""
    path = tmp_path / "body.npz"
    small_data.save_npz(path)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"body\.npz: not a readable npz body file"):
        BodyModelData.load_npz(path)


@pytest.mark.parametrize("num_vertices", [400, 500, 800, 900, 6890])
def test_a_small_random_body_skins_every_joint(num_vertices):
    """Under about 900 vertices the tubes listed last (arms, hands, head) were cut off: at 400,
    15 of the 24 joints carried no skin weight, so their rotations moved nothing."""
    data = random_body_data(num_vertices=num_vertices, with_posedirs=False)
    assert data.v_template.shape == (num_vertices, 3)
    assert (data.weights.sum(axis=0) > 0.5).all()
    assert data.faces.max() < num_vertices
    hand = data.joint_names.index("right_hand")
    assert (data.weights[:, hand] > 0).sum() >= 7  # at least one ring of its own tube


def test_an_unbatched_root_matrix_gets_a_hint(small_data):
    """A (3, 3) global_orient reads as three axis-angle rows; with another batch the error said
    only "global_orient has batch 3", with no word of why."""
    model = BodyModel(small_data, dtype=torch.float64)
    pose = torch.zeros(1, 23, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"one rotation matrix needs shape \(1, 3, 3\)"):
        model(None, pose, torch.eye(3, dtype=torch.float64))
    assert model(None, pose, torch.eye(3, dtype=torch.float64)[None]).vertices.shape[0] == 1
