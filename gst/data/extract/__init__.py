"""Scene extraction: videos + rig -> crop store + report (`extract_scene`).

Modules by phase: `masks` (per-camera foreground or person labels), `association` (people and
ids across cameras and time), `crops` (per-camera crops into part stores), `scene` (the
orchestration: plan, phases, merge, report) and `options` (settings, errors, the report).
"""

from typing import TYPE_CHECKING

from gst.lazy import lazy_exports

if TYPE_CHECKING:  # imported on first use (gst.lazy): worker processes stay light
    from gst.data.extract.crops import crop_person, extract_camera_crops, score_against_truth
    from gst.data.extract.masks import compute_camera_masks
    from gst.data.extract.options import CameraReport, ExtractError, ExtractOptions, ExtractReport
    from gst.data.extract.scene import extract_scene
    from gst.video import VideoError

__all__ = [
    "CameraReport",
    "ExtractError",
    "ExtractOptions",
    "ExtractReport",
    "VideoError",
    "compute_camera_masks",
    "crop_person",
    "extract_camera_crops",
    "extract_scene",
    "score_against_truth",
]

__getattr__, __dir__ = lazy_exports(__name__, __file__)
