"""The open default body against Anny itself (joints, vertices, axes, cache, parts, subsets)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gst.body import BodyModel
from gst.body import anny_default as ad
from gst.body.joint_limits import sample_body_pose
from gst.body.rotations import axis_angle_to_matrix
from gst.body.skeleton import INTERNAL_PART_NAMES, PART_NAMES, SMPL_JOINT_NAMES, SMPL_PARENTS
from gst.body.subsets import partition_vertices, vertex_subset


# Session scope: Anny is built once per test session. The first build on a machine takes about
# 30 s (plus Anny's own first build, about 60 s); once cached, a fraction of a second.
@pytest.fixture(scope="session")
def anny_data():
    """The open default body (built once, then loaded from the cache)."""
    return ad.build_anny_default()


@pytest.fixture(scope="session")
def anny_reference():
    """Anny itself, for comparisons."""
    return ad.AnnyReference()


def _betas_for(body: BodyModel, rest_vertices: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """Least-squares betas of Anny rest meshes (n, V_anny, 3) in the model's shape space."""
    dirs = body.shapedirs.reshape(-1, body.num_betas)
    resid = (rest_vertices[:, ids] - body.v_template).reshape(len(rest_vertices), -1)
    return torch.linalg.lstsq(dirs, resid.T).solution.T


def test_layout_licence_and_shape_space(anny_data):
    d = anny_data
    assert d.num_joints == 24 and d.joint_names == SMPL_JOINT_NAMES
    assert tuple(d.parents) == SMPL_PARENTS
    assert d.num_betas >= 10 and d.shapedirs.shape == (d.num_vertices, 3, d.num_betas)
    assert d.posedirs is None
    ratio = d.shape_variance_ratio
    assert (
        ratio.shape == (d.num_betas,)
        and np.all(np.diff(ratio) <= 0)
        and 0.99 < ratio[:10].sum() <= 1.0
    )
    assert np.all(np.diff(d.shape_variance) <= 0)
    assert "Apache-2.0" in d.licence and "CC0" in d.licence
    assert len(d.source_vertex_ids) == d.num_vertices and np.all(np.diff(d.source_vertex_ids) > 0)
    np.testing.assert_allclose(d.dense_J_regressor().sum(axis=1), 1.0, atol=1e-8)
    # every part is present, and the internal ones stay in the head
    counts = np.bincount(d.part_labels, minlength=len(PART_NAMES))
    assert np.all(counts > 0), dict(zip(PART_NAMES, counts, strict=True))
    internal = np.isin(d.part_labels, [PART_NAMES.index(p) for p in INTERNAL_PART_NAMES])
    assert (
        d.v_template[internal, 1].min()
        > d.dense_J_regressor()[SMPL_JOINT_NAMES.index("neck")] @ d.v_template[:, 1]
    )


def test_smpl_axes(anny_data):
    """Y up, facing +Z, body-left at +X, metres."""
    body = BodyModel(anny_data, dtype=torch.float64)
    j = body.J_template.numpy()
    idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    assert j[idx["head"], 1] > j[idx["neck"], 1] > j[idx["pelvis"], 1] > j[idx["left_knee"], 1]
    assert j[idx["left_hip"], 0] > 0 > j[idx["right_hip"], 0]
    assert j[idx["left_foot"], 2] > j[idx["left_ankle"], 2] + 0.05  # toes point forward
    height = np.ptp(anny_data.v_template[:, 1])
    assert 1.4 < height < 2.0


def test_matches_anny_posed_joints_and_vertices(anny_data, anny_reference):
    """100 random shapes from Anny's distribution and random poses within the joint limits: our
    joints against Anny's own posed bone heads, our vertices against Anny's posed mesh."""
    n = 100
    body = BodyModel(anny_data, dtype=torch.float64)
    ref = anny_reference
    g = torch.Generator().manual_seed(11)
    phen = ref.sample_phenotypes(n, (12.0, 80.0), seed=12345)
    rest_v, rest_heads = ref.rest(phen)
    ids = torch.as_tensor(anny_data.source_vertex_ids)
    betas = _betas_for(body, rest_v, ids)
    pose = sample_body_pose(n, generator=g, dtype=torch.float64)
    orient = axis_angle_to_matrix(0.7 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    anny_v, anny_heads = ref.posed(phen, torch.cat([orient[:, None], pose], dim=1))
    root = body.rest_joints(betas)[:, 0]
    out = body(betas, pose, orient, transl=-root)  # Anny keeps its root bone at the origin

    rest_err = (body.rest_joints(betas) - rest_heads).norm(dim=-1)
    joint_err = (out.joints - anny_heads).norm(dim=-1)
    vert_err = (out.vertices - anny_v[:, ids]).norm(dim=-1)
    print(
        f"\nrest joints: mean {1e3 * rest_err.mean():.2f} mm, max {1e3 * rest_err.max():.2f} "
        f"mm\nposed joints: mean {1e3 * joint_err.mean():.2f} mm, median "
        f"{1e3 * joint_err.median():.2f} mm, p95 {1e3 * joint_err.quantile(0.95):.2f} mm, max "
        f"{1e3 * joint_err.max():.2f} mm\nvertices: median {1e3 * vert_err.median():.2f} mm, p95 "
        f"{1e3 * vert_err.flatten().quantile(0.95):.2f} mm, max {1e3 * vert_err.max():.2f} mm"
    )
    assert joint_err.mean() < 5e-3
    assert joint_err.quantile(0.95) < 5e-3
    assert vert_err.median() < 5e-3


def test_identity_pose_is_the_anny_rest_mesh(anny_data, anny_reference):
    """Posing Anny with identity rotations leaves its rest mesh (root at the origin): our zero
    pose is Anny's rest pose, not SMPL's T-pose."""
    ref = anny_reference
    phen = ref.sample_phenotypes(2, (20.0, 60.0), seed=3)
    rest_v, rest_heads = ref.rest(phen)
    posed_v, _ = ref.posed(phen, torch.eye(3, dtype=torch.float64).expand(2, 24, 3, 3))
    torch.testing.assert_close(posed_v, rest_v - rest_heads[:, :1], rtol=0, atol=1e-9)


def test_cache_is_reused(anny_data, tmp_path, monkeypatch):
    """A second build with the same arguments reads the cached file and builds nothing."""
    monkeypatch.setattr(ad, "_build", lambda *a, **k: pytest.fail("rebuilt despite the cache"))
    again = ad.build_anny_default()
    np.testing.assert_array_equal(again.shapedirs, anny_data.shapedirs)
    np.testing.assert_array_equal(again.dense_J_regressor(), anny_data.dense_J_regressor())


def test_subsets_and_partition_on_anny(anny_data):
    internal = np.isin(anny_data.part_labels, [PART_NAMES.index(p) for p in INTERNAL_PART_NAMES])
    for preset, n in (("6890", 6890), ("3445", 3445), ("1723", 1723)):
        ids = vertex_subset(anny_data, preset)
        assert len(ids) == n and not internal[ids].any()
    ids = vertex_subset(anny_data, "6890")
    labels = partition_vertices(anny_data.v_template[ids], K=26)
    np.testing.assert_array_equal(np.bincount(labels), np.full(26, 265))
    assert len(vertex_subset(anny_data, "full")) == int((~internal).sum())


@pytest.mark.slow
def test_rebuild_in_another_cache_dir_is_identical(anny_data, tmp_path):
    """A fresh build (about 30 s) into another cache folder gives the same arrays: the build is
    deterministic, so the cache key describes the content."""
    fresh = ad.build_anny_default(cache_dir=tmp_path)
    assert len(list((tmp_path / "body").glob("anny-default-smpl24-*.npz"))) == 1
    for field in (
        "v_template",
        "shapedirs",
        "weights",
        "faces",
        "part_labels",
        "shape_variance_ratio",
    ):
        np.testing.assert_allclose(
            getattr(fresh, field), getattr(anny_data, field), rtol=0, atol=1e-12
        )
    np.testing.assert_allclose(
        fresh.dense_J_regressor(), anny_data.dense_J_regressor(), rtol=0, atol=1e-9
    )


def test_load_body_model_anny(anny_data):
    from gst.body import load_body_model

    body = load_body_model("anny")
    assert body.num_joints == 24 and body.num_vertices == anny_data.num_vertices
    assert body.dtype == torch.float32 and body.posedirs is None
