"""Where people are in each crop (gst.fuse.silhouettes) and its votes in the triangulation's pair
consensus: a point half the views agree on but that lands on nobody in the other half loses to
the point that lies on the person in every view."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_fuse_triangulate import _observe, _rig

from gst.fuse.silhouettes import CropSilhouettes, ViewSilhouettes, crop_silhouettes
from gst.fuse.triangulate import TriangulationOptions, project, triangulate_points
from tests.fuse_fixtures import windows_store

S = 64  # crop pixels


def test_a_crop_is_covered_where_anyone_of_its_camera_and_frame_is_or_outside_the_image(tmp_path):
    """Crop 0 (window x 0-64) sees its own block and crop 1's person (window x 32-96, twice the
    pixels per cell) pasted where they are in the image; crop 2 (another frame) and crop 3
    (another camera) are not pasted into it; a window hanging over the image's right edge is
    covered there."""
    masks = np.zeros((4, S, S), np.uint8)
    masks[0, 8:24, 8:24] = 255  # image x 8-24, y 8-24
    masks[1, 40:56, 40:56] = 255  # window (32, 0, 64): image x 52-60, y 20-28
    masks[2, 40:56, 8:24] = 255
    masks[3, 40:56, 8:24] = 255
    windows = [(0, 0, 64), (32, 0, 32), (0, 0, 64), (40, 0, 64)]
    store = windows_store(
        tmp_path / "c.h5", windows, masks, camera=[0, 0, 0, 1], frame=[0, 0, 1, 0]
    )
    sil = crop_silhouettes(store, {"a": (80, 64), "b": (80, 64)}, size=16)
    assert isinstance(sil, CropSilhouettes) and sil.masks.shape == (4, 16, 16)
    want = np.zeros((16, 16), bool)
    want[2:6, 2:6] = True  # its own person
    want[5:7, 13:15] = True  # crop 1's person, image x 52-60, y 20-28 (cells of 4 px)
    np.testing.assert_array_equal(sil.masks[0], want)
    want = np.zeros((16, 16), bool)
    want[10:14, 2:6] = True
    np.testing.assert_array_equal(sil.masks[2], want)  # frame 1: nobody else
    want = np.zeros((16, 16), bool)
    want[10:14, 2:6] = True
    want[:, 10:] = True  # camera b's window spans x 40-104: past the image from x 80
    np.testing.assert_array_equal(sil.masks[3], want)


def test_silhouette_votes_settle_an_even_split():
    """Three views read a point where it is, three read it somewhere else and agree with each
    other, more confidently. The pair consensus alone cannot tell them apart (it keeps the
    confident three); with the people's coverage of every view, the point that lies on someone
    in all six views wins."""
    rng = np.random.default_rng(4)
    K, Rt = _rig(6, rng)
    K[:, :2, 2] += 2000  # every projection inside the (large) crop
    N = 30
    X = rng.uniform([-1, -1, 0.5], [1, 1, 2], (N, 3))
    Y = X + rng.uniform(0.3, 0.5, (N, 3)) * rng.choice([-1, 1], (N, 3))  # the wrong reading
    Kb, Rtb, uv = _observe(K, Rt, X)
    _, _, uv_wrong = _observe(K, Rt, Y)
    bad = np.stack([rng.choice(6, 3, replace=False) for _ in range(N)])
    rows = np.arange(N)[:, None]
    uv = uv + rng.normal(0, 0.3, uv.shape)
    uv[rows, bad] = uv_wrong[rows, bad] + rng.normal(0, 0.3, (N, 3, 2))
    conf = np.full((N, 6), 0.7)
    conf[rows, bad] = 0.95
    size, crop = 64, 4096  # cells of 64 px
    masks = np.zeros((N, 6, size, size), bool)

    def cover(points, views):
        at, _ = project(np.broadcast_to(K @ Rt, (len(points), 6, 3, 4)), points)
        cells = np.floor(at * size / crop).astype(int)
        for n in range(N):
            for c in views[n]:
                masks[n, c, cells[n, c, 1], cells[n, c, 0]] = True

    cover(X, np.tile(np.arange(6), (N, 1)))  # the person is where X projects, in every view
    cover(Y, bad)  # and where the wrong views put it (they read it on someone)
    views = ViewSilhouettes.from_masks(masks, np.ones((N, 6), bool), np.arange(N), crop)
    o = TriangulationOptions(consensus_views=8)
    plain = triangulate_points(Kb, Rtb, uv, conf, options=o)
    voted = triangulate_points(Kb, Rtb, uv, conf, options=o, silhouettes=views)
    assert plain.used[rows, bad].all(1).mean() > 0.8  # the confident wrong three win
    assert not voted.used[rows, bad].any()  # every wrong view dropped
    assert (voted.used.sum(1) == 3).all()
    assert np.linalg.norm(voted.points - X, axis=1).max() < 0.02
    nobody = ViewSilhouettes.from_masks(
        np.zeros_like(masks), np.ones((N, 6), bool), np.arange(N), crop
    )
    same = triangulate_points(Kb, Rtb, uv, conf, options=o, silhouettes=nobody)
    np.testing.assert_array_equal(same.used, plain.used)  # no coverage: no votes


def test_views_without_a_crop_or_pixels_never_vote_and_the_outside_is_unknown():
    masks = np.zeros((1, 3, 8, 8), bool)
    masks[0, :, 2, 3] = True
    views = ViewSilhouettes.from_masks(masks, np.array([[True, True, False]]), np.array([0]), 80)
    uv = np.array([[[35.0, 25.0], [35.0, 25.0], [35.0, 25.0]]])  # cell (3, 2) in every view
    assert views.covered(np.array([0]), uv).tolist() == [[True, True, False]]
    uv = np.array([[[5.0, 5.0], [np.nan, np.nan], [500.0, 5.0]]])
    assert views.covered(np.array([0]), uv).tolist() == [[False, False, False]]
    outside = np.array([[[-5.0, 5.0], [85.0, 5.0], [5.0, 5.0]]])
    assert views.covered(np.array([0]), outside).tolist() == [[True, True, False]]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), size=st.sampled_from([8, 16, 64]))
def test_the_packed_lookup_reads_the_cell_each_pixel_falls_in(seed, size):
    """Silhouettes are kept as bits; `covered` must read the same cell as plain indexing."""
    rng = np.random.default_rng(seed)
    T, C, crop = 3, 4, 96
    masks = rng.random((T, C, size, size)) < 0.4
    has = rng.random((T, C)) < 0.8
    views = ViewSilhouettes.from_masks(masks, has, np.arange(T), crop)
    # 5 hypotheses a point, inside the crop (pixel centres at integers: edges at -0.5)
    uv = rng.uniform(-0.5, crop - 0.5, (T, 5, C, 2))
    cell = np.floor((uv + 0.5) * size / crop).astype(int)
    t, c = np.arange(T)[:, None, None], np.arange(C)[None, None, :]
    want = masks[t, c, cell[..., 1], cell[..., 0]] & has[t, c]
    np.testing.assert_array_equal(views.covered(np.arange(T), uv), want)
    crops = CropSilhouettes.from_masks(masks.reshape(-1, size, size), crop)
    np.testing.assert_array_equal(crops.masks, masks.reshape(-1, size, size))


def test_an_even_split_follows_the_frames_around_it():
    """Five frames of one point: at the middle frame three views read it where it is and three
    more confident ones agree on a point 0.4 m away; the frames around it are clean. The
    temporal vote (the mean of the first pass at t - 1 and t + 1) settles the tie."""
    from gst.fuse.observations import PersonObservations
    from gst.fuse.triangulate import triangulate_person

    rng = np.random.default_rng(7)
    K, Rt = _rig(6, rng)
    T, C, M = 5, 6, 33
    X = np.array([0.2, -0.1, 1.0]) + np.linspace(0, 0.08, T)[:, None] * [1, 0.5, 0]  # (T, 3)
    uv = np.full((T, C, M, 2), np.nan)
    conf = np.zeros((T, C, M))
    for t in range(T):
        uv[t, :, 0] = _observe(K, Rt, X[t : t + 1])[2][0] + rng.normal(0, 0.3, (C, 2))
        conf[t, :, 0] = 0.7
    wrong = X[2] + [0.4, 0.0, -0.3]
    bad = [1, 3, 5]
    uv[2, bad, 0] = _observe(K, Rt, wrong[None])[2][0, bad]
    conf[2, bad, 0] = 0.95
    obs = PersonObservations(
        1, np.arange(T), uv, conf, np.broadcast_to(K, (T, C, 3, 3)).copy(),
        np.broadcast_to(Rt, (T, C, 3, 4)).copy(), np.ones((T, C)), np.arange(T * C).reshape(T, C),
    )  # fmt: skip
    plain = triangulate_person(obs, TriangulationOptions(consensus_views=8))
    voted = triangulate_person(obs, TriangulationOptions(consensus_views=8, temporal_weight=1.0))
    assert np.linalg.norm(plain.points[2, 0] - wrong) < 0.02  # the confident three win alone
    assert np.linalg.norm(voted.points[2, 0] - X[2]) < 0.02
    assert voted.used[2, 0].tolist() == [True, False, True, False, True, False]
    np.testing.assert_allclose(voted.points[[0, 1, 3, 4], 0], plain.points[[0, 1, 3, 4], 0])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_a_pixel_is_covered_where_its_pooled_cell_is(seed):
    """Against OpenCV's pooling of a pixel mask into cells (INTER_AREA, as the store's masks
    are pooled): a point inside a masked pixel is covered exactly where that pixel's cell is.
    `covered` read the cell half a crop pixel to the left and above (cell k from pixel
    centres k f - 0.5 ...): a point in pixel 4 (cell 1 of 4-pixel cells) read cell 0."""
    rng = np.random.default_rng(seed)
    crop, size = 64, 16
    pixels = np.zeros((crop, crop), bool)
    x0, y0 = rng.integers(0, crop - 8, 2)
    pixels[y0 : y0 + 8, x0 : x0 + 8] = True
    cells = cv2.resize(pixels.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) > 0.5
    views = ViewSilhouettes.from_masks(
        cells[None, None], np.ones((1, 1), bool), np.zeros(1, int), crop
    )
    px = rng.integers(0, crop, (200, 2))  # pixels, and a point anywhere inside each
    uv = px + rng.uniform(-0.5, 0.5, px.shape)
    got = views.covered(np.zeros(len(uv), int), uv[:, None, :])[:, 0]
    want = cells[px[:, 1] * size // crop, px[:, 0] * size // crop]
    np.testing.assert_array_equal(got, want)
