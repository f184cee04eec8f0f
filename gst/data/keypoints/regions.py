"""Where to look for a person the detector missed: the landmark model's region of interest
from a 3D skeleton projected into a camera, and whether what it found is that person.

A person triangulated from some cameras (or predicted from the previous frames) is somewhere
definite in every other camera. The landmark model, given a tight region around that spot,
usually finds them even when the detector did not (crowds hide faces, which the detector keys
on); in a crowd the region also holds neighbours, so its answer is kept only when its landmarks
fit the projected skeleton.
"""

from __future__ import annotations

import numpy as np

from calibration.camera import Camera
from gst.data.keypoints.geometry import project
from gst.data.keypoints.instances import BODY_LANDMARKS, PersonInstance
from gst.data.keypoints.matching import MatchConfig, camera_view, fit_errors
from gst.detect.blazepose import BodyRoi, roi_from_alignment

_HIPS, _SHOULDERS = [23, 24], [11, 12]
_BODY = np.asarray(BODY_LANDMARKS)


def roi_from_skeleton(cam: Camera, skeleton: np.ndarray, margin: float = 1.05) -> BodyRoi | None:
    """The landmark model's region for a (33, 3) world skeleton in `cam`: centred on the hips,
    its radius the farthest projected landmark from them times `margin`, turned so that the
    hips-to-shoulders direction points up (as BlazePose's own alignment points). None when the
    hips or shoulders are unknown or behind the camera, the hips fall outside the image, or the
    region would be tiny or much larger than the image."""
    uv, _ = project(cam, np.asarray(skeleton, np.float64))
    ok = np.all(np.isfinite(uv), axis=1)
    if not ok[_HIPS + _SHOULDERS].all() or ok.sum() < 8:
        return None
    hip, shoulder = uv[_HIPS].mean(axis=0), uv[_SHOULDERS].mean(axis=0)
    if not (0 <= hip[0] < cam.width and 0 <= hip[1] < cam.height):
        return None
    radius = float(np.linalg.norm(uv[ok] - hip, axis=1).max()) * margin
    if not 4.0 <= radius <= 2.0 * max(cam.width, cam.height):
        return None  # a speck, or a skeleton reaching behind the camera
    up = shoulder - hip
    up = up / max(float(np.linalg.norm(up)), 1e-6)
    return roi_from_alignment(hip, hip + radius * up)


def skeleton_fit(
    cam: Camera, instance: PersonInstance, skeleton: np.ndarray, config: MatchConfig
) -> float:
    """Mean landmark error of `instance` against the projection of a (33, 3) skeleton, as a
    share of the instance's size (inf when too few landmarks compare)."""
    view = camera_view(cam, [instance], config.min_confidence)
    e, _ = fit_errors(np.asarray(skeleton, np.float64)[_BODY][None], view, config)
    return float(e[0, 0])
