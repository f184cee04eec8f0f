"""Vertex presets (farthest-point sampling) and the balanced, compact partition into K groups."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from gst.body.random_model import random_body_data
from gst.body.skeleton import PART_NAMES
from gst.body.subsets import farthest_point_order, partition_vertices, vertex_subset


@pytest.fixture(scope="module")
def smpl_sized():
    return random_body_data(num_vertices=6890, with_posedirs=False, seed=0)


@pytest.fixture(scope="module")
def big():
    """A mesh larger than 6890 with some vertices marked as inside the head."""
    data = random_body_data(num_vertices=9000, with_posedirs=False, seed=1)
    labels = np.asarray(data.part_labels).copy()
    labels[::50] = PART_NAMES.index("mouth_cavity")
    return data.replace(part_labels=labels)


def test_smpl_sized_6890_is_full(smpl_sized):
    full = vertex_subset(smpl_sized, "full")
    np.testing.assert_array_equal(full, np.arange(6890))
    np.testing.assert_array_equal(vertex_subset(smpl_sized, "6890"), full)
    assert len(vertex_subset(smpl_sized, "3445")) == 3445
    assert len(vertex_subset(smpl_sized, "1723")) == 1723


def test_presets_are_nested_sorted_stable_and_skip_internal(big):
    internal = np.flatnonzero(np.asarray(big.part_labels) == PART_NAMES.index("mouth_cavity"))
    subsets = {p: vertex_subset(big, p) for p in ("full", "6890", "3445", "1723")}
    assert len(subsets["full"]) == 9000 - len(internal)
    for preset, n in (("6890", 6890), ("3445", 3445), ("1723", 1723)):
        ids = subsets[preset]
        assert len(ids) == n and len(np.unique(ids)) == n and np.all(np.diff(ids) > 0)
        assert not np.isin(ids, internal).any()
    assert (
        np.isin(subsets["1723"], subsets["3445"]).all()
        and np.isin(subsets["3445"], subsets["6890"]).all()
    )
    # Deterministic: the same data gives the same ids (also when rebuilt from scratch).
    rebuilt = random_body_data(num_vertices=9000, with_posedirs=False, seed=1)
    rebuilt = rebuilt.replace(part_labels=np.asarray(big.part_labels))
    np.testing.assert_array_equal(vertex_subset(rebuilt, "3445"), subsets["3445"])
    with pytest.raises(ValueError, match="unknown vertex preset"):
        vertex_subset(big, "5000")


def test_fps_covers_the_mesh_better_than_random(big):
    """Farthest-point sampling: every vertex is close to a chosen one, and the chosen ones are
    spread out; both beat a random subset of the same size clearly."""
    v = np.asarray(big.v_template)
    ids = vertex_subset(big, "1723")
    random_ids = np.random.default_rng(0).choice(len(v), 1723, replace=False)
    cover = lambda s: cKDTree(v[s]).query(v)[0].max()  # noqa: E731
    spacing = lambda s: cKDTree(v[s]).query(v[s], k=2)[0][:, 1].min()  # noqa: E731
    assert cover(ids) < 0.6 * cover(random_ids)
    assert spacing(ids) > 3 * spacing(random_ids)


def test_farthest_point_order_reference():
    """Against a direct O(N^2) implementation."""
    pts = np.random.default_rng(2).normal(size=(300, 3))
    order = farthest_point_order(pts, 40)
    chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1)))]
    for _ in range(39):
        d = np.linalg.norm(pts[:, None] - pts[chosen][None], axis=2).min(axis=1)
        chosen.append(int(np.argmax(d)))
    np.testing.assert_array_equal(order, chosen)


@settings(max_examples=30, deadline=None)
@given(st.integers(30, 3000), st.integers(1, 30), st.integers(0, 3))
def test_partition_is_balanced(n, k, seed):
    if k > n:
        return
    pts = np.random.default_rng(seed).normal(size=(n, 3)) * [0.3, 0.9, 0.2]
    labels = partition_vertices(pts, K=k, seed=seed)
    sizes = np.bincount(labels, minlength=k)
    assert len(sizes) == k and sizes.max() - sizes.min() <= 1 and sizes.sum() == n


def test_partition_is_compact_and_deterministic(smpl_sized):
    v = np.asarray(smpl_sized.v_template)[vertex_subset(smpl_sized, "6890")]
    labels = partition_vertices(v, K=26)
    np.testing.assert_array_equal(labels, partition_vertices(v, K=26))
    np.testing.assert_array_equal(
        np.bincount(labels, minlength=26), np.full(26, 265)
    )  # as in the paper

    def spread(lab):  # mean distance of a vertex to its group's centroid
        cent = np.stack([v[lab == g].mean(0) for g in range(26)])
        return np.linalg.norm(v - cent[lab], axis=1).mean()

    random_labels = np.random.default_rng(0).permutation(labels)
    assert spread(labels) < 0.25 * spread(random_labels)


def test_partition_rejects_bad_input():
    with pytest.raises(ValueError, match=r"rest_vertices must have shape \(N, 3\)"):
        partition_vertices(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="K must lie in"):
        partition_vertices(np.zeros((10, 3)), K=11)
