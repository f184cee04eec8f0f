"""Learned person detection and segmentation for real footage (BlazePose through LiteRT).

Optional: needs the `detect` extra (ai-edge-litert) and the model files from
`python -m gst.detect fetch`. See docs/person_models.md.
"""

from gst.detect.weights import (
    BlazePoseModelsCorrupt,
    BlazePoseModelsMissing,
    fetch_blazepose_models,
    model_paths,
)

__all__ = [
    "BlazePoseModelsCorrupt",
    "BlazePoseModelsMissing",
    "fetch_blazepose_models",
    "model_paths",
]
