"""Association with instance masks (a learned person segmenter): two people who stand close
stay two people, and each camera's instance goes whole to its own person."""

import numpy as np
import pytest

from gst.data.association import AssociationConfig, CaptureVolume, VoxelGrid, associate_frame
from tests.extract_scenes import ring_rig


def _body_points(centre_xy, radius=0.2, height=1.7, n=4000, seed=0):
    """Points filling an upright cylinder (a coarse person)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, n)
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    z = rng.uniform(0, height, n)
    return np.stack([centre_xy[0] + r * np.cos(a), centre_xy[1] + r * np.sin(a), z], axis=1)


def _instance_labels(rig, people):
    """Per camera: a z-buffered label image, value k + 1 for people[k]; labels are numbered per
    camera in a shuffled order, as a segmenter would (no global ids)."""
    out = {}
    for ci, cam in enumerate(rig):
        depth = np.full((cam.height, cam.width), np.inf)
        lab = np.zeros((cam.height, cam.width), np.uint8)
        order = np.random.default_rng(ci).permutation(len(people)) + 1
        for k, pts in enumerate(people):
            uv = np.round(cam.project(pts)).astype(int)
            d = cam.to_camera(pts)[:, 2]
            ok = (
                (uv[:, 0] >= 0)
                & (uv[:, 0] < cam.width)
                & (uv[:, 1] >= 0)
                & (uv[:, 1] < cam.height)
                & (d > 0)
            )
            for (u, v), dd in zip(uv[ok], d[ok], strict=True):
                for dv in (-1, 0, 1):
                    for du in (-1, 0, 1):
                        y, x = v + dv, u + du
                        if 0 <= x < cam.width and 0 <= y < cam.height and dd < depth[y, x]:
                            depth[y, x], lab[y, x] = dd, order[k]
        out[cam.name] = (lab, order)
    return out


@pytest.mark.parametrize("gap", [0.5, 0.6])
def test_close_people_stay_apart_with_instance_masks(gap):
    rig = ring_rig(4, size=(320, 240), distort=False)
    people = [_body_points((-gap / 2, 0.0), seed=1), _body_points((gap / 2, 0.0), seed=2)]
    rendered = _instance_labels(rig, people)
    labels = {n: lab for n, (lab, _) in rendered.items()}
    sizes = {c.name: (c.width, c.height) for c in rig}
    volume = CaptureVolume.around((0.0, 0.0, 1.0), (2.0, 2.0, 1.2))
    cfg = AssociationConfig(instance_split=True)
    grid = VoxelGrid(list(rig), sizes, volume, cfg)
    result = associate_frame(grid, labels)
    assert len(result.persons) == 2
    centres = sorted(
        p.ground[0] if abs(p.ground[0]) > abs(p.ground[1]) else p.ground[1] for p in result.persons
    )
    assert centres[0] < 0 < centres[1]
    for name, (lab, order) in rendered.items():
        pl = result.labels[name]
        for k in range(2):
            inst = lab == order[k]
            owner = np.bincount(pl[inst], minlength=3)
            # the instance goes whole to one person, and the two instances to different people
            assert owner.max() >= 0.97 * inst.sum(), (name, k, owner)
        owners = {int(np.bincount(pl[lab == order[k]], minlength=3).argmax()) for k in range(2)}
        assert owners == {1, 2}


def test_instance_split_never_splits_one_person():
    rig = ring_rig(4, size=(320, 240), distort=False)
    rendered = _instance_labels(rig, [_body_points((0.3, -0.2), seed=3)])
    labels = {n: lab for n, (lab, _) in rendered.items()}
    grid = VoxelGrid(
        list(rig),
        {c.name: (c.width, c.height) for c in rig},
        CaptureVolume.around((0.0, 0.0, 1.0), (2.0, 2.0, 1.2)),
        AssociationConfig(instance_split=True),
    )
    assert len(associate_frame(grid, labels).persons) == 1
