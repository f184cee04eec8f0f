"""Camera corrections from the fitted bodies (gst.fuse.rig): a camera whose believed rotation is
1.5 degrees off is found and turned back; the reprojection error drops to the noise and the
bodies come closer to the truth."""

from __future__ import annotations

import numpy as np
import torch

from gst.body import load_body_model
from gst.body.markers import MarkerModel
from gst.fuse.fit import fit_people
from gst.fuse.rig import apply_corrections, camera_corrections, rotation_matrix
from gst.fuse.triangulate import triangulate_person
from tests.fuse_fixtures import make_capture, observations

torch.set_num_threads(1)


def test_a_turned_camera_is_found_and_put_back():
    body = load_body_model("anny")
    cap = make_capture(body, n_people=2, n_frames=5, n_cams=5, seed=21)
    people = observations(cap, noise_px=0.5, seed=1)
    w0 = np.deg2rad(1.5) * np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
    wrong = np.zeros((5, 3))
    wrong[2] = w0
    apply_corrections(people, wrong)  # what we believe about camera 2 is 1.5 degrees off
    markers = MarkerModel.load()

    def fit():
        tris = [triangulate_person(p) for p in people]
        fits = fit_people(body, markers, people, tris, 30.0)
        reproj = float(np.nanmedian(np.concatenate([f.reprojection.ravel() for f in fits])))
        joints = np.linalg.norm(np.stack([f.joints for f in fits]) - cap.joints, axis=-1).mean()
        return fits, reproj, joints

    fits, before, joints_before = fit()
    w = camera_corrections(fits, people, 5)
    # camera 2 is turned back, the others hardly move (the mean turn is the world's)
    err = rotation_matrix(w[2]) @ rotation_matrix(w0)
    left = np.degrees(np.arccos(np.clip((np.trace(err) - 1) / 2, -1, 1)))
    assert left < 0.3, left
    assert np.degrees(np.linalg.norm(np.delete(w, 2, 0), axis=1)).max() < 0.25
    apply_corrections(people, w)
    _, after, joints_after = fit()
    assert after < before and after < 0.6, (before, after)  # 0.5 px of noise: its floor
    assert joints_after < 0.8 * joints_before, (joints_before, joints_after)


def test_the_corrected_rig_keeps_its_up_axis_and_metadata():
    """`corrected_rig` rebuilt the rig from its cameras only: a Y-down Panoptic world came back
    with up +Z and no metadata in `FuseResult.rig`."""
    from calibration.camera import Camera, Rig
    from gst.fuse.rig import corrected_rig

    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cams = [
        Camera.create(name, K, np.zeros(5), np.eye(3), [x, 0.0, 3.0], 640, 480)
        for name, x in (("a", 0.0), ("b", 1.0))
    ]
    rig = Rig(cams, up=(0.0, -1.0, 0.0), meta={"source": "panoptic"})
    out = corrected_rig(rig, ["b"], np.array([[0.0, 0.01, 0.0]]))
    assert out.up == (0.0, -1.0, 0.0) and out.meta == {"source": "panoptic"}
    np.testing.assert_allclose(out.cameras[0].R, np.eye(3))
    np.testing.assert_allclose(out.cameras[1].R, rotation_matrix(np.array([0.0, 0.01, 0.0])))


def test_nobody_fitted_corrects_no_camera():
    """The stage's readable people can be none (every view projected): the camera rounds then
    turn no camera, as without them (they indexed the first person and crashed)."""
    np.testing.assert_array_equal(camera_corrections([], [], 4), np.zeros((4, 3)))
