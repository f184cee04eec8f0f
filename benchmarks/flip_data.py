"""A workspace's crops as the flip-check benchmarks read them: BlazePose's landmarks and, against
a reference (the synthetic truth, or the fuse stage's bodies), which side each reading puts
right (`gst.metrics.flips.landmark_sides`: +1 right, -1 mirrored, 0 unsure or no reference)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from gst.eval.scene import fused_reference  # noqa: E402
from gst.metrics.flips import landmark_sides, reference_in_crops  # noqa: E402
from gst.train.keypoints import store_landmarks  # noqa: E402
from gst.train.scene_truth import attach_scene_truth  # noqa: E402
from gst.train.views import CropSet, load_cropset  # noqa: E402


def labelled_scene_crops(ws: Path, reference: str) -> tuple[CropSet, torch.Tensor, np.ndarray]:
    """(crops with their reference in `truth`, (N, 33, 3) landmarks, (N,) sides) of the scene
    workspace `ws` (WS/<scene>); `reference` "truth" (needs `synth/`) or "fused" (`fused/`)."""
    crops, boxes = load_cropset(ws / "crops" / "crops.h5")
    lm, _ = store_landmarks(ws / "crops" / "crops.h5", crops.images)
    if reference == "truth":
        attach_scene_truth(crops, boxes, ws / "synth")
    else:
        bodies = ws / "fused" / "bodies.parquet"  # not landmarks.parquet, which sits beside it
        if not bodies.is_file():
            raise SystemExit(f"{bodies} not found: run the fuse stage first")
        fused_reference(crops, bodies)
    ok = crops.truth["has_truth"].numpy()
    ref = reference_in_crops(crops.truth["joints_world"], crops.R, crops.t, crops.K)
    return crops, lm.float(), np.where(ok, landmark_sides(lm.numpy(), ref), 0)
