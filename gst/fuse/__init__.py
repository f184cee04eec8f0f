"""The rig as the measuring instrument: one world-space body per person and frame.

    from gst.fuse import fuse_scene, FuseOptions
    result = fuse_scene("workspace/demo/crops/crops.h5", rig, "out/fused", "out/reports")

Modules: observations (landmarks per crop, grouped per person), consensus (which views show
the person), regroup (people regrouped by 3D agreement and tracked), triangulate (robust
N-view triangulation), silhouettes (where people are in each crop: votes in the triangulation
and an optional fit term), start (the fit's starting pose), fit (the body fit over the clip) with
gst.body.kinematics (joints-only body forward and its Jacobian), objective (the energy and its
linearisation) and solver (batched Levenberg-Marquardt), joint_map (landmark -> joint table),
tables (Parquet), export (TRC, C3D), overlay, report, evaluate (against synthetic truth),
scene (the entry point), marker_data and fit_markers (fitting gst.body.markers on synthetic
worlds; the worlds' detections come from gst.lift.marker_worlds), body_labels and body_crops
(crops cut again from the fitted bodies) and rounds (the fuse stage's recipe: fuse, cut,
fuse again, cut).
"""

from gst.fuse.consensus import ConsensusOptions, view_consensus
from gst.fuse.fit import FitOptions, PersonFit, fit_people
from gst.fuse.regroup import RegroupOptions, regroup_people
from gst.fuse.scene import FuseOptions, FuseResult, fuse_scene
from gst.fuse.triangulate import TriangulationOptions, triangulate_person, triangulate_points

__all__ = [
    "ConsensusOptions",
    "FitOptions",
    "FuseOptions",
    "FuseResult",
    "PersonFit",
    "RegroupOptions",
    "TriangulationOptions",
    "fit_people",
    "fuse_scene",
    "regroup_people",
    "triangulate_person",
    "triangulate_points",
    "view_consensus",
]
