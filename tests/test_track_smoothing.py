"""One-Euro filter against a plain scalar transcription of the published formula."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gst.track.smoothing import (
    OneEuroConfig,
    OneEuroFilter,
    PoseSmoother,
    rot6d_to_rotmat,
    rotmat_to_6d,
)


def reference_one_euro(xs, ts, min_cutoff, beta, d_cutoff):
    """Casiez et al. 2012, one scalar at a time, written without numpy."""

    def alpha(cutoff, te):
        tau = 1.0 / (2 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / te)

    out, x_prev, dx_prev, t_prev = [], None, 0.0, None
    for x, t in zip(xs, ts, strict=True):
        if x_prev is None:
            x_prev, t_prev = x, t
            out.append(x)
            continue
        te = t - t_prev
        dx = (x - x_prev) / te
        a_d = alpha(d_cutoff, te)
        dx_hat = a_d * dx + (1 - a_d) * dx_prev
        cutoff = min_cutoff + beta * abs(dx_hat)
        a = alpha(cutoff, te)
        x_hat = a * x + (1 - a) * x_prev
        out.append(x_hat)
        x_prev, dx_prev, t_prev = x_hat, dx_hat, t
    return out


@settings(max_examples=40, deadline=None)
@given(st.floats(0.05, 5), st.floats(0, 3), st.floats(0.1, 5), st.integers(0, 10_000))
def test_matches_reference_elementwise_with_irregular_times(min_cutoff, beta, d_cutoff, seed):
    rng = np.random.default_rng(seed)
    n = 60
    ts = np.cumsum(rng.uniform(0.01, 0.1, n))  # dropped frames / stride: uneven steps
    xs = np.cumsum(rng.normal(0, 0.05, (n, 4, 3)), axis=0) + rng.normal(0, 0.02, (n, 4, 3))
    cfg = OneEuroConfig(min_cutoff, beta, d_cutoff)
    f = OneEuroFilter(cfg)
    ours = np.stack([f(x, t) for x, t in zip(xs, ts, strict=True)])
    for idx in [(0, 0), (1, 2), (3, 1)]:
        ref = reference_one_euro(
            xs[(slice(None), *idx)].tolist(), ts.tolist(), min_cutoff, beta, d_cutoff
        )
        np.testing.assert_allclose(ours[(slice(None), *idx)], ref, rtol=1e-12, atol=1e-12)


def test_state_round_trip_continues_identically():
    import json

    rng = np.random.default_rng(3)
    xs, ts = rng.normal(size=(40, 5)), np.arange(40) / 30.0
    cfg = OneEuroConfig(1.0, 0.3, 1.0)
    a = OneEuroFilter(cfg)
    full = [a(x, t) for x, t in zip(xs, ts, strict=True)]
    b = OneEuroFilter(cfg)
    for x, t in zip(xs[:17], ts[:17], strict=True):
        b(x, t)
    c = OneEuroFilter(cfg)
    c.load_state_dict(json.loads(json.dumps(b.state_dict())))
    rest = [c(x, t) for x, t in zip(xs[17:], ts[17:], strict=True)]
    np.testing.assert_array_equal(np.stack(rest), np.stack(full[17:]))


def test_reduces_jitter_and_follows_motion():
    rng = np.random.default_rng(4)
    t = np.arange(300) / 30.0
    truth = np.where(t < 5, 0.0, 2.0 * (t - 5))  # at rest, then moving at 2 m/s
    noisy = truth + rng.normal(0, 0.02, t.size)
    f = OneEuroFilter(OneEuroConfig(min_cutoff=0.5, beta=1.0, d_cutoff=1.0))
    smooth = np.array([f(np.array([x]), ti)[0] for x, ti in zip(noisy, t, strict=True)])
    rest = slice(30, 150)
    assert np.std(smooth[rest]) < 0.3 * np.std(noisy[rest])
    assert np.abs(smooth[-30:] - truth[-30:]).mean() < 0.1  # little lag once the speed is known


def test_rotations_stay_rotations_and_6d_round_trips():
    R = Rotation.random(50, random_state=0).as_matrix()
    np.testing.assert_allclose(rot6d_to_rotmat(rotmat_to_6d(R)), R, atol=1e-12)
    sm = PoseSmoother(OneEuroConfig(0.5, 0.1, 1.0))
    rng = np.random.default_rng(5)
    for i in range(20):
        rot = Rotation.from_rotvec(rng.normal(0, 0.5, (24, 3))).as_matrix()
        out = sm(
            7,
            i / 30,
            {
                "rotmats": rot,
                "betas": np.zeros(10),
                "transl_cam": np.zeros(3),
                "joints_cam": np.zeros((24, 3)),
            },
        )
        np.testing.assert_allclose(
            out["rotmats"] @ out["rotmats"].transpose(0, 2, 1),
            np.broadcast_to(np.eye(3), (24, 3, 3)),
            atol=1e-12,
        )
        np.testing.assert_allclose(np.linalg.det(out["rotmats"]), 1.0, atol=1e-12)
    sm.retain(set())
    assert sm.filters == {}


def test_a_sample_that_is_not_finite_passes_through_and_leaves_the_state_alone():
    """One NaN sample made the state NaN, and every later output NaN, for good."""
    cfg = OneEuroConfig(min_cutoff=1.0, beta=0.5, d_cutoff=1.0)
    xs = [np.array([0.0, 1.0]), np.array([0.1, 1.2]), np.array([np.nan, 1.1]), np.array([0.3, 1.0])]
    f, skip = OneEuroFilter(cfg), OneEuroFilter(cfg)
    got = [f(x, t) for t, x in enumerate(xs)]
    want = [skip(x, t) for t, x in enumerate(xs) if np.isfinite(x).all()]
    assert np.isnan(got[2][0]) and got[2][1] == 1.1
    np.testing.assert_array_equal(got[3], want[2])
    g = OneEuroFilter(cfg)
    g(np.array([np.nan, 0.0]), 0.0)
    np.testing.assert_array_equal(g(np.array([2.0, 3.0]), 1.0), [2.0, 3.0])  # the first value
