"""Synthetic multi-camera capture with exact ground truth.

    from synth import preset, render_scene
    summary = render_scene(preset("demo"), "workspace/demo/synth")  # replaced whole

Modules: `rigs` (camera rigs), `stage` (room), `motions` (procedural sports motions),
`people` (shapes, outfits, placement), `animate` (posing through a body model), `appearance`
(per-part colours), `render` (Embree mesh renderer), `board` (ChArUco clip), `imaging` (camera
response), `truth` (Parquet tables), `shares` (camera shares, the unit of serial or fanned-out
rendering), `scene` (specs, presets, `render_scene`).
World convention: metres, Z up, floor z = 0 (see `synth.world`).
"""

from synth.motions import MOTIONS, MotionClip, generate_motion, random_static_poses
from synth.rigs import make_rig
from synth.scene import PRESETS, SceneSpec, SceneSummary, preset, render_scene

__all__ = [
    "MOTIONS",
    "PRESETS",
    "MotionClip",
    "SceneSpec",
    "SceneSummary",
    "generate_motion",
    "make_rig",
    "preset",
    "random_static_poses",
    "render_scene",
]
