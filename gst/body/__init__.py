"""Body models in SMPL layout: LBS, official SMPL files, and the open default built from Anny.

    from gst.body import load_body_model
    body = load_body_model("anny")                 # open default, no licence needed
    body = load_body_model("~/models/SMPL_NEUTRAL.pkl")   # your own SMPL copy
    out = body(betas, body_pose, global_orient, transl, return_transforms=True)

See docs/body_model.md for conventions, licences and accuracy.
"""

from __future__ import annotations

from pathlib import Path

import torch

from gst.body.model import BodyModel, BodyModelData, BodyOutput, open_npz
from gst.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)

__all__ = [
    "BodyModel",
    "BodyModelData",
    "BodyOutput",
    "body_model_file",
    "load_body_model",
    "load_body_data",
    "rot6d_to_matrix",
    "matrix_to_rot6d",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
]


def load_body_data(spec: str = "anny") -> BodyModelData:
    """The arrays of a body model. ``spec``:

    - ``"anny"``: the open default (built once from Anny, then cached);
    - ``"smpl"``, ``"smpl:male"``, ``"smpl:female"``: official SMPL from ``$GST_BODY_DIR`` or
      ``~/.cache/gst-capture/body/``;
    - a path: an SMPL file (.pkl/.npz), a folder holding ``SMPL_NEUTRAL.pkl``, or an .npz
      written by ``BodyModelData.save_npz``.
    """
    from gst.body.smpl_file import load_smpl_file

    if spec == "anny":
        from gst.body.anny_default import build_anny_default

        return build_anny_default()
    if spec == "smpl" or spec.startswith("smpl:"):
        return load_smpl_file(None, gender=spec.partition(":")[2] or None)
    path = Path(spec).expanduser()
    if path.suffix == ".npz" and path.is_file():
        with open_npz(path, ".npz body or SMPL file") as z:
            ours = "format" in z.files
        if ours:
            return BodyModelData.load_npz(path)
    return load_smpl_file(path)


def body_model_file(spec: str) -> Path | None:
    """The file a body-model ``spec`` (see :func:`load_body_data`) reads, or None: the built-in
    Anny default, or a spec that names no existing file (loading it says why). Its content is
    what a fit or a network made with the spec depends on (the pipeline hashes it)."""
    from gst.body.smpl_file import find_smpl_file

    if spec == "anny":
        return None
    try:
        if spec == "smpl" or spec.startswith("smpl:"):
            return find_smpl_file(None, spec.partition(":")[2] or None)
        path = Path(spec).expanduser()
        return path if path.suffix == ".npz" and path.is_file() else find_smpl_file(path, None)
    except (FileNotFoundError, ValueError):
        return None


def load_body_model(
    spec: str = "anny", device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> BodyModel:
    """A ready :class:`BodyModel` for ``spec`` (see :func:`load_body_data`)."""
    return BodyModel(load_body_data(spec), dtype=dtype, device=device)
