"""Per-part appearance: body parts from the skeleton agree with the model's own part labels,
and kit pieces land where they belong."""

import numpy as np
import pytest
from synth_fixtures import CapsuleBody

from synth.animate import rest_pose
from synth.appearance import REGIONS, BodyAtlas, albedo, sample_outfit, srgb_to_linear, team_kits
from synth.people import sample_people

BODY = CapsuleBody()
REST_V, REST_J = rest_pose(BODY, np.zeros(10, np.float32))
# The stand-in's own part labels, in synth's region names (an independent segmentation).
_TO_REGION = {
    "head": "head",
    "neck": "neck",
    "torso": "trunk",
    "hips": "trunk",
    "upperarm": "upperarm",
    "forearm": "forearm",
    "hand": "hand",
    "upperleg": "upperleg",
    "lowerleg": "lowerleg",
    "foot": "foot",
}
TRUE_REGION = np.array([REGIONS.index(_TO_REGION[BODY.part_names[i]]) for i in BODY.part_labels])


def _vertex_albedo(outfit, atlas, idx):
    """Albedo evaluated exactly at vertices (one-hot barycentrics)."""
    tri = np.stack([idx, idx, idx], -1)
    bary = np.tile([1.0, 0.0, 0.0], (len(idx), 1))
    return albedo(outfit, atlas, tri, bary)


def test_skeleton_segmentation_agrees_with_model_part_labels():
    atlas = BodyAtlas.build(REST_V, REST_J)  # geometry only, no labels
    agree = atlas.region == TRUE_REGION
    # The stand-in's capsules overlap at every joint, where "nearest bone" and "which capsule"
    # legitimately differ; away from joints they agree.
    assert agree.mean() > 0.8
    for region in ("head", "upperarm", "forearm", "hand", "upperleg", "lowerleg", "foot"):
        sel = TRUE_REGION == REGIONS.index(region)
        assert agree[sel].mean() > 0.7, f"{region}: {agree[sel].mean():.0%} agree"
    # With the model's labels, extremities follow them exactly.
    labelled = BodyAtlas.build(REST_V, REST_J, BODY.part_labels, BODY.part_names)
    for region in ("head", "hand", "foot"):
        sel = TRUE_REGION == REGIONS.index(region)
        assert np.all(labelled.region[sel] == REGIONS.index(region))


def test_unusable_part_labels_fall_back_to_geometry():
    atlas = BodyAtlas.build(REST_V, REST_J, np.zeros(len(REST_V), int), ["mystery"])
    assert np.array_equal(atlas.region, BodyAtlas.build(REST_V, REST_J).region)
    with pytest.raises(ValueError, match="part_labels"):
        BodyAtlas.build(REST_V, REST_J, np.zeros(5, int), ["head"])


def test_kit_pieces_land_on_the_right_parts():
    atlas = BodyAtlas.build(REST_V, REST_J, BODY.part_labels, BODY.part_names)
    kit = dict(
        jersey=(200, 20, 30),
        jersey_second=(20, 60, 170),
        pattern="solid",
        shorts=(15, 25, 60),
        socks=(245, 200, 20),
        trim=(245, 245, 245),
        sleeve=0.5,
    )
    outfit = sample_outfit(np.random.default_rng(0), kit, 0)
    outfit = type(outfit)(
        **{
            **outfit.__dict__,
            "number": 7,
            "hair_style": "short",
            "shoes": (30, 30, 30),
            "skin": (198, 134, 98),
        }
    )
    idx = np.arange(len(REST_V))
    col = _vertex_albedo(outfit, atlas, idx)

    def share(region_name, rgb, where=None):
        sel = TRUE_REGION == REGIONS.index(region_name)
        if where is not None:
            sel &= where
        return np.all(np.isclose(col[sel], srgb_to_linear(rgb), atol=1e-6), axis=1).mean()

    y = REST_V[:, 1]
    knee_y = REST_J[4, 1]
    ankle_y = REST_J[7, 1]
    assert share("upperleg", outfit.shorts, y > REST_J[1, 1] - 0.05) > 0.9  # top of the thighs
    assert (
        share("lowerleg", outfit.socks, (y > ankle_y + 0.02) & (y < ankle_y + 0.1)) > 0.9
    )  # above the ankles
    assert (
        share("lowerleg", outfit.skin, (y > knee_y - 0.06) & (y < knee_y)) > 0.8
    )  # just below the knee
    assert share("foot", outfit.shoes) + share("foot", (235, 235, 235)) > 0.95  # shoe or sole
    assert share("forearm", outfit.skin) > 0.95  # short sleeves
    chest = (TRUE_REGION == REGIONS.index("trunk")) & (y > REST_J[3, 1] + 0.05) & (y < REST_J[9, 1])
    jersey_or_number = np.isclose(col[chest], srgb_to_linear(outfit.jersey), atol=1e-6).all(
        1
    ) | np.isclose(col[chest], srgb_to_linear(outfit.trim), atol=1e-6).all(1)
    assert jersey_or_number.mean() > 0.8
    # The number is printed on the back (trim colour), and there is hair on top of the head.
    back = chest & (REST_V[:, 2] < REST_J[9, 2])
    assert np.isclose(col[back], srgb_to_linear(outfit.trim), atol=0.05).all(1).mean() > 0.05
    top = (TRUE_REGION == REGIONS.index("head")) & (
        y > np.percentile(y[TRUE_REGION == REGIONS.index("head")], 85)
    )
    assert share("head", outfit.hair, top) > 0.9


def test_teams_share_kits_and_people_differ():
    rng = np.random.default_rng(3)
    people = sample_people(4, rng, 10, (0, 0, 0.9), 1.5, 60, 30.0, n_teams=2)
    assert [p.person_id for p in people] == [1, 2, 3, 4]
    assert people[0].outfit.jersey == people[2].outfit.jersey
    assert people[0].outfit.jersey != people[1].outfit.jersey
    assert len({tuple(p.betas) for p in people}) == 4
    again = sample_people(4, np.random.default_rng(3), 10, (0, 0, 0.9), 1.5, 60, 30.0, n_teams=2)
    assert [p.to_dict() for p in again] == [p.to_dict() for p in people]
    kits = team_kits(3, np.random.default_rng(0))
    assert len({k["jersey"] for k in kits}) == 3


def test_people_start_inside_the_volume():
    people = sample_people(
        6,
        np.random.default_rng(1),
        10,
        (0.5, -0.5, 0.9),
        2.0,
        90,
        30.0,
        programmes=[
            ["run"],
            ["walk", "run"],
            ["squat"],
            ["jump", "kick"],
            ["throw"],
            ["random_static"],
        ],
    )
    for p in people:
        assert np.hypot(p.start[0] - 0.5, p.start[1] + 0.5) <= 2.0
        clip = p.motion_clip(90, 30.0, seed=0)
        assert np.all(np.hypot(clip.position[:, 0] - 0.5, clip.position[:, 1] + 0.5) < 2.5)
    with pytest.raises(ValueError, match="unknown motions"):
        sample_people(
            1, np.random.default_rng(0), 10, (0, 0, 0), 1.0, 10, 30.0, programmes=[["moonwalk"]]
        )
