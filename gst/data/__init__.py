"""Data preparation for GST: masks, multi-view person association, crops and the crop store.

Entry points:
- `extract_scene(videos, rig, out_h5, ...)` does the whole job and returns an `ExtractReport`;
  `write_extract_report(report, store_path, out_dir)` writes markdown and a contact sheet.
- `CropStore(path)` reads a store: `select(...)`, `multiview_groups(...)`, `read(rows)`.
- Building blocks: background models (`background`), mask clean-up (`masks`), visual-hull
  association (`associate`), crops with their own intrinsics (`crop`), external masks
  (`external`), truth scores (`evaluate`).
"""

from typing import TYPE_CHECKING

from gst.lazy import lazy_exports

if TYPE_CHECKING:  # imported on first use (gst.lazy): worker processes stay light
    from gst.data.association import AssociationConfig, CaptureVolume, PersonTracker, VoxelGrid
    from gst.data.background import BackgroundConfig, build_background
    from gst.data.crop import CropBox, crop_camera, crop_intrinsics, extract_crop, hmr_crop_box
    from gst.data.external import ExternalDetections, ExternalError, IdMaskFile, read_external
    from gst.data.extract import (
        CameraReport,
        ExtractError,
        ExtractOptions,
        ExtractReport,
        crop_person,
        extract_scene,
    )
    from gst.data.masks import MaskConfig, clean_mask
    from gst.data.report import ExtractReportFiles, contact_sheet, write_extract_report
    from gst.data.store import CropBatch, CropStore, CropStoreWriter, MultiViewGroup, StoreError
    from gst.video import VideoError, VideoInfo, check_videos, probe_video, read_frames

__all__ = [
    "AssociationConfig",
    "BackgroundConfig",
    "CameraReport",
    "CaptureVolume",
    "CropBatch",
    "CropBox",
    "CropStore",
    "CropStoreWriter",
    "ExternalDetections",
    "ExternalError",
    "ExtractError",
    "ExtractOptions",
    "ExtractReport",
    "ExtractReportFiles",
    "IdMaskFile",
    "MaskConfig",
    "MultiViewGroup",
    "PersonTracker",
    "StoreError",
    "VideoError",
    "VideoInfo",
    "VoxelGrid",
    "build_background",
    "check_videos",
    "clean_mask",
    "contact_sheet",
    "crop_camera",
    "crop_intrinsics",
    "crop_person",
    "extract_crop",
    "extract_scene",
    "hmr_crop_box",
    "probe_video",
    "read_external",
    "read_frames",
    "write_extract_report",
]

__getattr__, __dir__ = lazy_exports(__name__, __file__)
