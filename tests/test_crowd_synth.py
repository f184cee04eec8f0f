"""The crowd layout of the synthetic world: people who come within 0.5 m of each other, never
closer than a torso, inside the volume; walkers crossing; the rendered truth agrees."""

import numpy as np
import pyarrow.parquet as pq
import pytest
from synth_fixtures import CapsuleBody, rig_io

from synth.crowd import CrowdConfig, closest_approach, path, place_crowd
from synth.motions import generate_motion
from synth.people import sample_crowd
from synth.scene import preset, render_scene

CENTER, RADIUS = (0.0, 0.0, 0.95), 1.5


def _crowd(seed: int, n: int, frames: int = 48, fps: float = 30.0):
    rng = np.random.default_rng(np.random.SeedSequence([seed, 1]))
    people = sample_crowd(n, rng, 10, CENTER, RADIUS, frames, fps, seed)
    paths = [p.motion_clip(frames, fps, seed).position for p in people]
    return people, paths


@pytest.mark.parametrize("seed", [5000, 5001, 5002, 5003])
@pytest.mark.parametrize("n", [3, 4, 6])
def test_everyone_comes_close_to_someone_but_never_through_them(seed, n):
    people, paths = _crowd(seed, n)
    near = closest_approach(paths)
    assert near.min(axis=1).max() < 0.5  # each person comes within 0.5 m of someone
    p = np.stack(paths)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + 9 * np.eye(n)[:, :, None]
    assert (d.min(axis=1) < 0.5).mean() > 0.2  # and often: a fifth of the time at least
    assert near.min() >= CrowdConfig().min_gap - 1e-9
    r = np.linalg.norm(np.stack(paths) - np.asarray(CENTER[:2]), axis=-1)
    assert r.max() <= RADIUS
    walkers = [p for p in people if "walk" in p.motions]
    assert len(walkers) >= 2  # paths cross
    # Walkers move through the crowd: each covers at least a metre in 1.6 s.
    for p, xy in zip(people, paths, strict=True):
        if "walk" in p.motions:
            assert np.linalg.norm(xy[-1] - xy[0]) > 1.0


def test_placement_is_the_played_clip():
    """A placement chosen on the origin clip is exactly where the person is played."""
    rng = np.random.default_rng(3)
    clips = [generate_motion(["walk"], 30, 30.0, np.random.default_rng(k)) for k in range(3)]
    places = place_crowd(clips, rng, CENTER, RADIUS)
    for k, pl in enumerate(places):
        again = generate_motion(
            ["walk"], 30, 30.0, np.random.default_rng(k), start=pl.start, heading=pl.heading
        )
        np.testing.assert_allclose(again.position, path(clips[k], pl), atol=1e-9)


def test_crowd_is_deterministic_and_validated():
    a, _ = _crowd(7000, 5)
    b, _ = _crowd(7000, 5)
    assert [p.to_dict() for p in a] == [p.to_dict() for p in b]
    with pytest.raises(ValueError, match="min_gap"):
        CrowdConfig(min_gap=0.6)
    with pytest.raises(ValueError, match="unknown motions"):
        sample_crowd(
            2, np.random.default_rng(0), 10, CENTER, RADIUS, 10, 30.0, 0, [["walk"], ["fly"]]
        )
    spec = preset("crowd", seed=7001)
    assert spec.layout == "crowd" and 3 <= spec.n_people <= 6


def test_rendered_crowd_truth_matches_the_layout(tmp_path):
    """Rendered (capsule bodies, 2 tiny cameras): the truth pelvis paths are the planned ones."""
    spec = preset(
        "crowd",
        seed=5004,
        n_people=3,
        n_frames=8,
        rig=dict(n_cameras=2, width=96, height=72),
        board=dict(n_frames=0),
        imaging=dict(antialias=1, background_samples=1, shadow_samples=1, write_depth=False),
    )
    write_rig, _ = rig_io()
    body = CapsuleBody()
    render_scene(spec, tmp_path / "s", body_model=body, rig_writer=write_rig)
    t = pq.read_table(tmp_path / "s" / "truth" / "people.parquet").to_pandas()
    joints = np.stack(t.joints3d).reshape(-1, 24, 3)
    truth = [joints[t.person_id.values == k][:, 0, :2] for k in (1, 2, 3)]
    rng = np.random.default_rng(np.random.SeedSequence([5004, 1]))
    planned = sample_crowd(3, rng, body.num_betas, CENTER, RADIUS, 8, 30.0, 5004)
    for p, xy in zip(planned, truth, strict=True):
        np.testing.assert_allclose(p.motion_clip(8, 30.0, 5004).position, xy, atol=1e-4)
