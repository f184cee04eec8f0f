"""Virtual markers: where on the body each BlazePose landmark lies, as a function of the pose.

BlazePose's "hip" is not the body model's hip joint: it is a point on the body whose place
depends on the person and the pose. A :class:`MarkerModel` anchors every landmark at one joint
of the SMPL skeleton, at an offset that turns with one joint's frame (the anchor itself or a
joint up the chain), expressed in that frame's rest axes (SMPL axes: x body-left, y up,
z forward, metres):

    marker_m = J_a + R_f @ offset_m        (a = anchor[m], f = frame[m], R_f its world rotation)

With f = a this is `A_a @ (J_a^rest + offset_m)` (A the skinning transforms of
:class:`gst.body.BodyOutput`): the point is rigidly attached to the anchor's bone. Anchoring at
the joint but turning with the parent's frame (e.g. BlazePose's ankle follows the shin, not the
foot) keeps bone lengths out of the offsets, so the table holds for any body shape. It is
differentiable in pose, shape and translation and cheap (no mesh). The form fits any body model
in SMPL layout, but a table's offsets are in the rest axes of the body it was fitted on: the
shipped one is the Anny default's (`info.body_model`; its rest arms hang about 45 degrees down),
and on an SMPL T-pose body its hand markers lie 6-8 cm off. `fitted_for` says so; fit a table
for another body with `python -m gst.fuse.fit_markers --body ...`.

    from gst.body.markers import MarkerModel
    markers = MarkerModel.load()                                   # the fitted default
    out = body(betas, body_pose, global_orient, transl, vertex_ids=markers.vertex_ids,
               return_transforms=True)
    xyz = markers.positions(out)                                   # (B, 33, 3)

The default parameters (`markers_blazepose.json` beside this file) were fitted on BlazePose
detections in rendered synthetic worlds (tuning seeds 5000+) by `python -m gst.fuse.fit_markers`,
which documents the data and the residuals in the JSON itself. Without that file the table
falls back to landmark = joint (`BODY_FROM_BLAZEPOSE` of gst.train.keypoints) and rough
anatomical offsets for the face, hands and feet.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from gst.body.model import BodyOutput
from gst.body.skeleton import SMPL_JOINT_NAMES

__all__ = [
    "BLAZEPOSE_NAMES",
    "BLAZEPOSE_MIRROR",
    "MarkerModel",
    "DEFAULT_PARENTS",
    "default_markers_path",
]

BLAZEPOSE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip


def _mirror_partner(name: str) -> int:
    return BLAZEPOSE_NAMES.index(
        name.replace("left", "@").replace("right", "left").replace("@", "right")
    )


# each landmark's index with left and right exchanged (the nose is its own); read-only
BLAZEPOSE_MIRROR = np.array([_mirror_partner(n) for n in BLAZEPOSE_NAMES])
BLAZEPOSE_MIRROR.flags.writeable = False

# landmark -> (parent joint, rough rest-frame offset in metres): the fallback table.
_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
DEFAULT_PARENTS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "nose": ("head", (0.0, 0.04, 0.10)),
    "left_eye_inner": ("head", (0.015, 0.07, 0.09)),
    "left_eye": ("head", (0.03, 0.07, 0.085)),
    "left_eye_outer": ("head", (0.045, 0.07, 0.08)),
    "right_eye_inner": ("head", (-0.015, 0.07, 0.09)),
    "right_eye": ("head", (-0.03, 0.07, 0.085)),
    "right_eye_outer": ("head", (-0.045, 0.07, 0.08)),
    "left_ear": ("head", (0.075, 0.05, 0.0)),
    "right_ear": ("head", (-0.075, 0.05, 0.0)),
    "mouth_left": ("head", (0.025, 0.0, 0.09)),
    "mouth_right": ("head", (-0.025, 0.0, 0.09)),
    "left_shoulder": ("left_shoulder", (0.0, 0.0, 0.0)),
    "right_shoulder": ("right_shoulder", (0.0, 0.0, 0.0)),
    "left_elbow": ("left_elbow", (0.0, 0.0, 0.0)),
    "right_elbow": ("right_elbow", (0.0, 0.0, 0.0)),
    "left_wrist": ("left_wrist", (0.0, 0.0, 0.0)),
    "right_wrist": ("right_wrist", (0.0, 0.0, 0.0)),
    "left_pinky": ("left_wrist", (0.07, -0.05, -0.02)),
    "right_pinky": ("right_wrist", (-0.07, -0.05, -0.02)),
    "left_index": ("left_wrist", (0.08, -0.05, 0.02)),
    "right_index": ("right_wrist", (-0.08, -0.05, 0.02)),
    "left_thumb": ("left_wrist", (0.04, -0.03, 0.04)),
    "right_thumb": ("right_wrist", (-0.04, -0.03, 0.04)),
    "left_hip": ("left_hip", (0.0, 0.0, 0.0)),
    "right_hip": ("right_hip", (0.0, 0.0, 0.0)),
    "left_knee": ("left_knee", (0.0, 0.0, 0.0)),
    "right_knee": ("right_knee", (0.0, 0.0, 0.0)),
    "left_ankle": ("left_ankle", (0.0, 0.0, 0.0)),
    "right_ankle": ("right_ankle", (0.0, 0.0, 0.0)),
    "left_heel": ("left_ankle", (0.0, -0.05, -0.05)),
    "right_heel": ("right_ankle", (0.0, -0.05, -0.05)),
    "left_foot_index": ("left_foot", (0.0, -0.02, 0.08)),
    "right_foot_index": ("right_foot", (0.0, -0.02, 0.08)),
}


def default_markers_path() -> Path:
    return Path(__file__).with_name("markers_blazepose.json")


class MarkerModel(torch.nn.Module):
    """Landmark positions on a posed body: `positions(body_output) -> (B, M, 3)`.

    Parameters: `anchors` (M,) joint index per marker, `frames` (M,) the joint whose rotation
    turns the offset (default: the anchor), `offsets` (M, 3) rest-frame offsets in metres.
    `offsets` is a buffer (fixed); make it a Parameter to fit it by gradient.
    """

    def __init__(
        self,
        names: tuple[str, ...] | list[str],
        anchors: list[int] | np.ndarray,
        offsets: np.ndarray,
        info: dict | None = None,
        frames: list[int] | np.ndarray | None = None,
    ) -> None:
        super().__init__()
        self.names = tuple(names)
        M = len(self.names)
        anchors = np.asarray(anchors, np.int64)
        frames = anchors if frames is None else np.asarray(frames, np.int64)
        offsets = np.asarray(offsets, np.float64)
        if anchors.shape != (M,) or frames.shape != (M,) or offsets.shape != (M, 3):
            raise ValueError(
                f"MarkerModel: {M} names need anchors ({M},), frames ({M},) and offsets "
                f"({M}, 3), got {anchors.shape}, {frames.shape} and {offsets.shape}"
            )
        # JSON reads NaN and Infinity: such a table loaded and put its markers at NaN
        if not np.all(np.isfinite(offsets)):
            bad = [self.names[i] for i in np.nonzero(~np.isfinite(offsets).all(1))[0]]
            raise ValueError(f"MarkerModel: offsets of {bad} are NaN or Inf")
        for what, idx in (("anchors", anchors), ("frames", frames)):
            if idx.min() < 0 or idx.max() >= len(SMPL_JOINT_NAMES):
                raise ValueError(f"MarkerModel: {what} must index the 24 SMPL joints, got {idx}")
        self.register_buffer("anchors", torch.as_tensor(anchors))
        self.register_buffer("frames", torch.as_tensor(frames))
        self.register_buffer("offsets", torch.as_tensor(offsets, dtype=torch.float32))
        self.info = dict(info or {})
        # The body forward must pose at least one vertex; markers need none (joints only).
        self.vertex_ids = torch.zeros(1, dtype=torch.long)

    def __len__(self) -> int:
        return len(self.names)

    def positions(self, out: BodyOutput) -> torch.Tensor:
        """(B, M, 3) world positions; `out` must come from
        `forward(..., return_transforms=True)`."""
        if out.joint_transforms is None:
            raise ValueError(
                "MarkerModel.positions needs the body's joint transforms "
                "(call the body model with return_transforms=True)"
            )
        return self.at(out.joints, out.joint_transforms[..., :3, :3])

    def at(self, joints: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
        """(B, M, 3) marker positions from the joints (B, 24, 3) and the joints' frames
        (B, 24, 3, 3), both in one frame of reference (world, or a camera's)."""
        rot = rotations[:, self.frames]  # (B, M, 3, 3)
        off = self.offsets.to(rot.dtype)
        return joints[:, self.anchors] + (rot @ off[None, :, :, None])[..., 0]

    # -- persistence ------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {
            "format": "gst-markers",
            "version": 1,
            "convention": "marker = joint[anchor] + R[frame] @ offset; offset in the frame "
            "joint's rest axes, SMPL axes (x left, y up, z forward), metres",
            "markers": [
                {
                    "name": n,
                    "anchor": SMPL_JOINT_NAMES[int(a)],
                    "frame": SMPL_JOINT_NAMES[int(f)],
                    "offset": [round(float(v), 5) for v in o],
                }
                for n, a, f, o in zip(
                    self.names,
                    self.anchors.tolist(),
                    self.frames.tolist(),
                    self.offsets.double().numpy(),
                    strict=True,
                )
            ],
            "info": self.info,
        }

    @classmethod
    def from_json(cls, doc: dict, where: str = "markers JSON") -> MarkerModel:
        if doc.get("format") != "gst-markers":
            raise ValueError(f"{where}: not a gst-markers file (format {doc.get('format')!r})")
        names, anchors, frames, offsets = [], [], [], []
        for m in doc["markers"]:
            for key in ("anchor", "frame"):
                if m.get(key) not in _J:
                    raise ValueError(
                        f"{where}: marker {m.get('name')!r} has {key} {m.get(key)!r}, expected "
                        "an SMPL joint name"
                    )
            names.append(m["name"])
            anchors.append(_J[m["anchor"]])
            frames.append(_J[m["frame"]])
            offsets.append(m["offset"])
        try:
            return cls(names, anchors, np.array(offsets), doc.get("info"), frames)
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None

    @classmethod
    def fallback(cls) -> MarkerModel:
        """Landmark = joint for the limbs, rough offsets for face, hands and feet (unfitted)."""
        anchors = [_J[DEFAULT_PARENTS[n][0]] for n in BLAZEPOSE_NAMES]
        offsets = np.array([DEFAULT_PARENTS[n][1] for n in BLAZEPOSE_NAMES])
        return cls(BLAZEPOSE_NAMES, anchors, offsets, {"fitted": False})

    def fitted_for(self, body_model: str) -> str | None:
        """None when this table was fitted on `body_model` (a body-model spec) or says nothing
        of its body; else a warning that its offsets belong to another body's rest pose."""
        fitted = self.info.get("body_model")
        if fitted is None or fitted == body_model:
            return None
        return (
            f"the marker table was fitted on the body '{fitted}', not '{body_model}': its "
            "offsets are in that body's rest axes (Anny's arms hang about 45 degrees down, "
            "SMPL's stand in a T), so hand and foot markers can lie several cm off; fit one "
            f"for this body with `python -m gst.fuse.fit_markers --body {body_model} ...`"
        )

    @classmethod
    def load(cls, path: str | Path | None = None) -> MarkerModel:
        """The fitted table at `path` (default: the package's), or the fallback if absent."""
        p = Path(path) if path is not None else default_markers_path()
        if not p.is_file():
            if path is not None:
                raise FileNotFoundError(f"markers file {p} does not exist")
            return cls.fallback()
        return cls.from_json(json.loads(p.read_text()), str(p))
