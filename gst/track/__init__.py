"""Tracking: per-frame inference on a video, written as pose time series to Parquet."""

from gst.data.camera_view import TrackingView, default_camera, focal_from_35mm
from gst.data.crop import CropWindow, crop_intrinsics, crop_window, cut_crop, cut_undistorted_crop
from gst.track.baseline import BoxDepthPredictor
from gst.track.batch import VideoJob, VideoOutcome, track_videos
from gst.track.chunks import ChunkingConfig
from gst.track.detection import Detection, Detector, SuppliedBoxes, SuppliedBoxesError
from gst.track.loop import TrackOptions, TrackResult, track_video
from gst.track.mirror import MirrorConfig
from gst.track.predictor import PoseBatch, Predictor, PredictorOutputError, validate_prediction
from gst.track.read import column_array, long_format, read_metadata, read_tracks
from gst.track.report import draw_people, joint_angles, plot_joint_angles, write_overlay
from gst.track.schema import SMPL_JOINT_NAMES, tracks_schema
from gst.track.smoothing import OneEuroConfig, OneEuroFilter, PoseSmoother
from gst.track.tracker import Observation, Tracker, TrackerConfig, box_iou
from gst.track.writer import ResumeError, TrackWriter
from gst.video import VideoError, VideoInfo, VideoTruncatedError, iter_frames, probe_video

__all__ = [
    "BoxDepthPredictor",
    "ChunkingConfig",
    "CropWindow",
    "Detection",
    "Detector",
    "MirrorConfig",
    "Observation",
    "OneEuroConfig",
    "OneEuroFilter",
    "PoseBatch",
    "PoseSmoother",
    "Predictor",
    "PredictorOutputError",
    "ResumeError",
    "SMPL_JOINT_NAMES",
    "SuppliedBoxes",
    "SuppliedBoxesError",
    "TrackOptions",
    "TrackResult",
    "TrackWriter",
    "Tracker",
    "TrackerConfig",
    "TrackingView",
    "VideoError",
    "VideoInfo",
    "VideoTruncatedError",
    "box_iou",
    "column_array",
    "crop_intrinsics",
    "crop_window",
    "cut_crop",
    "cut_undistorted_crop",
    "default_camera",
    "draw_people",
    "focal_from_35mm",
    "iter_frames",
    "joint_angles",
    "long_format",
    "plot_joint_angles",
    "write_overlay",
    "probe_video",
    "read_metadata",
    "read_tracks",
    "track_video",
    "tracks_schema",
    "validate_prediction",
    "VideoJob",
    "VideoOutcome",
    "track_videos",
]
