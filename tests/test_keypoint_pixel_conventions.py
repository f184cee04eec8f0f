"""Keypoint association's masks and boxes: a refined mask never takes a nearer person's pixels,
and the work-resolution ownership and mask boxes use the pixel-centre convention of the
landmarks (full-resolution pixel u sits at (u + 0.5) s - 0.5 at scale s)."""

from __future__ import annotations

import h5py
import numpy as np

from calibration.camera import Camera
from gst.data.extract.keypoint_association import _frame_instances, _write
from gst.data.keypoints import PersonInstance
from gst.data.keypoints.ownership import OwnershipConfig, own_pixels
from gst.data.keypoints.people import CrowdConfig, CrowdTracker

S, W, H = 0.25, 480, 270


def _look_at(name, pos, target=(0, 0, 1.0), f=1000.0, w=1920, h=1080):
    pos = np.asarray(pos, float)
    z = np.asarray(target, float) - pos
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    K = np.array([[f, 0, w / 2 - 0.3], [0, f * 1.01, h / 2 + 0.7], [0, 0, 1]])
    return Camera.create(name, K, np.zeros(5), R, -R @ pos, w, h)


def _rig():
    return [_look_at("c0", [6, 0, 2.5]), _look_at("c1", [0, 6, 2.6]),
            _look_at("c2", [-6, 0.5, 2.4]), _look_at("c3", [0.3, -6, 2.5])]  # fmt: skip


def _standing(centre):
    """A plausible standing BlazePose skeleton (33, 3), feet at z = 0 near `centre`."""
    pts = {0: (0, 0.08, 1.62), 7: (0.07, 0, 1.6), 8: (-0.07, 0, 1.6), 11: (0.19, 0, 1.42),
           12: (-0.19, 0, 1.42), 13: (0.24, 0, 1.12), 14: (-0.24, 0, 1.12), 15: (0.26, 0.05, 0.86),
           16: (-0.26, 0.05, 0.86), 23: (0.11, 0, 0.95), 24: (-0.11, 0, 0.95),
           25: (0.12, 0.03, 0.52), 26: (-0.12, 0.03, 0.52), 27: (0.12, 0, 0.1),
           28: (-0.12, 0, 0.1), 29: (0.12, -0.05, 0.05), 30: (-0.12, -0.05, 0.05),
           31: (0.12, 0.15, 0.03), 32: (-0.12, 0.15, 0.03)}  # fmt: skip
    X = np.zeros((33, 3))
    for k in range(33):
        if k in pts:
            X[k] = pts[k]
        elif k <= 10:
            X[k] = (0.03 * ((k % 3) - 1), 0.08, 1.62 + 0.01 * (k % 2))
        else:
            X[k] = (0.27 if k in (17, 19, 21) else -0.27, 0.07, 0.8)
    return X + np.asarray(centre, float)


def test_a_refined_mask_leaves_a_nearer_persons_pixels_to_them(tmp_path):
    """Camera c0: the far person's view is refined (the landmark model's segmentation, here
    generous: their whole landmark box), the near one's detected (ownership). Only overlaps
    between refined masks were settled; the writer then gave the shared pixels to whoever came
    first: 340 of the near person's pixels were written to the person 2.4 m behind."""
    cams = _rig()
    far, near = _standing((-1.0, 0.1, 0)), _standing((1.5, 0.0, 0))  # c0 stands at x = +6

    def segment(n, img, roi, origin):
        cam = next(c for c in cams if c.name == n)
        centre = np.array(roi.centre) + origin
        X = min((far, near), key=lambda X: np.linalg.norm(
            (cam.project(X)[[23, 24]].mean(0) + 0.5) * S - 0.5 - centre))  # fmt: skip
        if n == "c0" and X is near:
            return None  # the near person is not refined in c0
        lm = (cam.project(X) + 0.5) * S - 0.5 - origin
        yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
        lo, hi = lm.min(0), lm.max(0)
        box = (xx >= lo[0] - 2) & (xx <= hi[0] + 2) & (yy >= lo[1] - 2) & (yy <= hi[1] + 2)
        return np.c_[lm, np.full(33, 0.9)], 0.9, box.astype(np.float32)

    tracker = CrowdTracker(cams, 1 / 30, CrowdConfig(), segment, S)
    insts = {c.name: [PersonInstance.create(np.c_[c.project(X), np.full(33, 0.9)])
                      for X in (far, near)] for c in cams}  # fmt: skip
    fg = {c.name: np.ones((H, W), bool) for c in cams}
    img = {c.name: np.zeros((H, W, 3), np.uint8) for c in cams}
    res = tracker.process(0, insts, fg, img, img, None)
    c0 = cams[0]
    depth = {p.pid: c0.to_camera(p.skeleton[[11, 12, 23, 24]].mean(0)[None])[0, 2]
             for p in res.people}  # fmt: skip
    front = min(depth, key=depth.get)
    views = {p.pid: p.views["c0"] for p in res.people}
    assert {v.source for v in views.values()} == {"refined", "detected"}
    names = [c.name for c in cams]
    _write([res], names, {n: (W, H) for n in names}, [0], tmp_path, {n: (S, S) for n in names}, 1)
    with h5py.File(tmp_path / "persons_c0.h5") as f:
        lab, slots = f["labels"][0], f["slots"][()]
    pid_of = {int(s): int(p) for _, s, p in slots}
    written_front = np.isin(lab, [s for s, p in pid_of.items() if p == front])
    assert (views[front].mask <= written_front).all()  # every pixel of theirs is theirs


def test_ownership_discs_sit_where_their_pixel_centres_are():
    """A landmark disc at full-resolution pixel (100, 60) was owned around (50, 30) at scale
    0.5 (u s): its pixel centre there is (49.75, 29.75) ((u + 0.5) s - 0.5)."""
    cam = _rig()[0]
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
