"""Cameras, rig file formats, board detection, bundle adjustment and triangulation.

Submodules (import what you need; heavy dependencies load on use):
    camera       Camera, Rig, project_points_torch
    formats      read_rig, write_rig, FORMATS (rig.json, Panoptic, H36M, anipose, Pose2Sim,
                 Qualisys, COLMAP)
    board        BoardSpec, BoardDetector, detect_in_sources
    solve        calibrate_from_board, calibrate_from_detections, BoardCalibration
    triangulate  triangulate_dlt, triangulate_robust
    checks       CaptureVolume, check_rig
    report       write_calibration_report
    synthetic    synthetic board footage with known truth
"""

from calibration.camera import Camera, CameraError, Rig, look_at_rotation, project_points_torch

__all__ = ["Camera", "CameraError", "Rig", "look_at_rotation", "project_points_torch"]
