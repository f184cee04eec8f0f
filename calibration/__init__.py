"""Cameras, rig file formats, board detection, bundle adjustment and triangulation."""

from calibration.camera import Camera, CameraError, Rig

__all__ = ["Camera", "CameraError", "Rig"]
