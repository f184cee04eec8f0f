"""Keypoint association's work-resolution ownership and mask boxes use the pixel-centre
convention of the landmarks (full-resolution pixel u sits at (u + 0.5) s - 0.5 at scale s)."""

from __future__ import annotations

import h5py
import numpy as np

from gst.data.extract.keypoint_association import _frame_instances
from gst.data.keypoints import PersonInstance
from gst.data.keypoints.ownership import OwnershipConfig, own_pixels
from tests.crowd_people import rig


def test_ownership_discs_sit_where_their_pixel_centres_are():
    """A landmark disc at full-resolution pixel (100, 60) was owned around (50, 30) at scale
    0.5 (u s): its pixel centre there is (49.75, 29.75) ((u + 0.5) s - 0.5)."""
    cam = rig().cameras[0]  # a 2D-only person: any camera
    lm = np.zeros((33, 3))
    lm[7], lm[8] = (0, 60, 1), (200, 60, 1)  # the head: a disc at their mean, (100, 60)
    cfg = OwnershipConfig(step=1, reach=1.0, pixel_radius=0.04)
    for scale, shape in ((1.0, (200, 300)), (0.5, (100, 150)), (0.25, (50, 75))):
        o = own_pixels(cam, np.ones(shape, bool), [None], [lm], cfg, scale=scale)
        ys, xs = np.nonzero(o.labels == 1)
        want = (np.array([100.0, 60.0]) + 0.5) * scale - 0.5
        assert np.allclose([xs.mean(), ys.mean()], want, atol=0.1), scale  # old: 0.25, 0.375 off


def test_a_mask_box_and_a_landmark_box_of_the_same_pixels_agree(tmp_path):
    """Boxes from phase 1's masks were (x_min / s, ..., (x_max + 1) / s): half a full-resolution
    pixel right and down of PersonInstance boxes from landmarks (pixel-centre convention)."""
    lm = np.zeros((33, 3))
    lm[:, 2] = 1
    lm[:, 0], lm[:, 1] = np.linspace(10, 20, 33), np.linspace(30, 50, 33)
    lab = np.zeros((1, 60, 40), np.uint8)
    lab[0, 30:51, 10:21] = 1
    with h5py.File(tmp_path / "p.h5", "w") as f:
        f["labels"], f["landmarks"], f["presence"] = lab, lm[None, None], np.ones((1, 1))
    with h5py.File(tmp_path / "p.h5") as f:
        full, _ = _frame_instances(f, 0, 1.0, 1.0, "cam")
        half, _ = _frame_instances(f, 0, 0.5, 0.5, "cam")
    assert np.allclose(full[0].box, PersonInstance.create(lm).box)
    assert np.allclose(half[0].box, (19.5, 59.5, 41.5, 101.5))


def test_the_landmark_box_leaves_out_unseen_limbs_beyond_the_frame():
    """A person cut off by the frame's bottom edge: the model puts the ankles below it with a
    visibility near 0, and those grew the crop's landmark box 2.6 times (the person shrank in
    their crop by as much). A landmark outside the frame counts only when confident; inside
    it, any detected one does (a leg hidden behind someone still belongs in the crop)."""
    from gst.data.extract.keypoint_association import _extra_box

    lm = np.zeros((33, 3))
    lm[:, 0] = np.linspace(800, 1100, 33)
    lm[:, 1] = np.linspace(700, 1070, 33)
    lm[:, 2] = 0.9
    lm[27:29] = (950, 1560, 1e-4)  # the ankles, unseen, 480 px below a 1920 x 1080 frame
    lm[5] = (900, 650, 0.05)  # an eye hidden behind someone, inside the frame
    box = _extra_box(lm, 0.5, 0.5, (1920, 1080), 0.3)
    assert box[3] == (1070 + 0.5) * 0.5 and box[1] == (650 + 0.5) * 0.5
    lm[27:29, 2] = 0.8  # confidently placed beyond the edge: kept
    assert _extra_box(lm, 0.5, 0.5, (1920, 1080), 0.3)[3] == (1560 + 0.5) * 0.5
