"""From network outputs to a posed body and posed Gaussians, in camera and world frames.

Geometry (paper Sec. 3, with the public code's defects fixed):
- Camera: HMR2's (s, tx, ty) is read in the INPUT CROP's own camera: translation
  t = (tx, ty, 2 fx / (S s)) with fx from that crop's intrinsics (not a fixed 5000 px).
- Body: LBS with the predicted global orientation (camera frame) and body pose, translated by t.
- Gaussians sit on the LBS vertices of the chosen subset. Rest-frame offsets are posed with each
  vertex's skinning transform (mu = v + A_v delta), and each Gaussian's rotation is composed with
  the orthonormalised skinning rotation, so clothing detail moves with the limb it belongs to.
- World: X_world = R_in^T (X_cam - t_in) through the input camera's extrinsics.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from gst.body import BodyModel
from gst.body.rotations import rot6d_to_matrix
from gst.model.network import GaussianParams, GSTOutput


@dataclass
class PosedGaussians:
    means: torch.Tensor  # (B, V, 3)
    quats: torch.Tensor  # (B, V, 4) wxyz
    scales: torch.Tensor  # (B, V, 3)
    opacities: torch.Tensor  # (B, V)
    colors: torch.Tensor  # (B, V, 3)
    offsets: torch.Tensor  # (B, V, 3) rest-frame offsets (for the tightness loss)


@dataclass
class BodyPrediction:
    rotmats: torch.Tensor  # (B, 24, 3, 3); [:, 0] is the global orientation in the input camera
    betas: torch.Tensor  # (B, nb)
    transl_cam: torch.Tensor  # (B, 3)
    joints_cam: torch.Tensor  # (B, 24, 3) metres, input camera frame
    vertices_cam: torch.Tensor | None  # (B, V', 3)
    joints_world: torch.Tensor | None = None  # (B, 24, 3) when the input camera's pose is known
    # (B, 24, 3, 3) each joint's frame in the input camera (the skinning rotations), when the
    # body was posed with its transforms (with Gaussians): for virtual markers on the body
    joint_rotations_cam: torch.Tensor | None = None
    gaussians_cam: PosedGaussians | None = None
    gaussians_world: PosedGaussians | None = None
    # the network's Gaussians before posing (rest-frame offsets and rotations), so that they can
    # be posed on another body (gst.train.teacher_render)
    gaussian_params: GaussianParams | None = None


def camera_translation(cam: torch.Tensor, K_crop: torch.Tensor, crop_size: int) -> torch.Tensor:
    """(s, tx, ty) -> (tx, ty, 2 fx / (S s)); s is clamped away from 0 for stability."""
    s = cam[:, 0].clamp_min(1e-2)
    tz = 2.0 * K_crop[:, 0, 0] / (crop_size * s)
    return torch.stack([cam[:, 1], cam[:, 2], tz], dim=-1)


def _orthonormalise(m: torch.Tensor) -> torch.Tensor:
    """Nearest-rotation surrogate for blended skinning matrices: Gram-Schmidt of the first two
    columns (the 6D map), stable and cheap; exact when the blend is already a rotation."""
    return rot6d_to_matrix(torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1))


def to_world(points_cam: torch.Tensor, R_in: torch.Tensor, t_in: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) camera points -> world, with world-to-camera R_in (B, 3, 3), t_in (B, 3)."""
    return (points_cam - t_in[:, None]) @ R_in


def pose_gaussians(
    g: GaussianParams, vertices: torch.Tensor, vertex_transforms: torch.Tensor
) -> PosedGaussians:
    """Gaussians on posed vertices (B, V, 3) with their skinning transforms (B, V, 4, 4): the
    rest-frame offset and rotation of each go through its vertex's skinning (module doc)."""
    skin = vertex_transforms[..., :3, :3]
    means = vertices + (skin @ g.offsets[..., None])[..., 0]
    rot = _orthonormalise(skin) @ quaternion_to_rotation_matrix(g.quats)
    return PosedGaussians(
        means,
        rotation_matrix_to_quaternion(rot, eps=1e-12),
        g.scales,
        g.opacities,
        g.colors,
        g.offsets,
    )


def _gaussians_to_world(
    g: PosedGaussians, R_in: torch.Tensor, t_in: torch.Tensor
) -> PosedGaussians:
    rot_cam = quaternion_to_rotation_matrix(g.quats)
    rot_world = R_in.transpose(1, 2)[:, None] @ rot_cam
    return PosedGaussians(
        to_world(g.means, R_in, t_in),
        rotation_matrix_to_quaternion(rot_world, eps=1e-12),
        g.scales,
        g.opacities,
        g.colors,
        g.offsets,
    )


def _cast_output(out: GSTOutput, dtype: torch.dtype) -> GSTOutput:
    """The network's outputs in `dtype` (under bf16 autocast some of them come out in bf16)."""
    cast = {
        f.name: getattr(out, f.name).to(dtype)
        for f in dataclasses.fields(out)
        if f.name != "gaussians"
    }
    g = out.gaussians
    if g is not None:
        g = GaussianParams(**{f.name: getattr(g, f.name).to(dtype) for f in dataclasses.fields(g)})
    return GSTOutput(**cast, gaussians=g)


def assemble(
    out: GSTOutput,
    body: BodyModel,
    K_crop: torch.Tensor,
    crop_size: int,
    *,
    vertex_ids: torch.Tensor | None = None,
    R_in: torch.Tensor | None = None,
    t_in: torch.Tensor | None = None,
    with_vertices: bool = False,
) -> BodyPrediction:
    """Pose the body (and the Gaussians, when the network produced them), in the body's dtype.

    World coordinates need both extrinsics: `R_in` without `t_in`, or the reverse, is refused
    (it gave no world coordinates, silently).

    Runs with autocast disabled: under bf16 autocast (``TrainConfig.amp``) only the network runs
    in reduced precision; skinning and posing in bf16 (about 3 significant digits, i.e.
    centimetres a few metres from the camera) would be too coarse, and would hand the
    rasteriser a mix of dtypes.
    """
    if (R_in is None) != (t_in is None):
        raise ValueError(
            "assemble: world coordinates need the input camera's R and t together, got only "
            + ("R" if t_in is None else "t")
        )
    with torch.autocast(body.device.type, enabled=False):
        return _assemble(
            _cast_output(out, body.dtype),
            body,
            K_crop.to(body.dtype),
            crop_size,
            vertex_ids=vertex_ids,
            R_in=None if R_in is None else R_in.to(body.dtype),
            t_in=None if t_in is None else t_in.to(body.dtype),
            with_vertices=with_vertices,
        )


def _assemble(
    out: GSTOutput,
    body: BodyModel,
    K_crop: torch.Tensor,
    crop_size: int,
    *,
    vertex_ids: torch.Tensor | None,
    R_in: torch.Tensor | None,
    t_in: torch.Tensor | None,
    with_vertices: bool,
) -> BodyPrediction:
    transl = camera_translation(out.cam, K_crop, crop_size)
    want_gaussians = out.gaussians is not None
    body_out = body(
        out.betas,
        out.rotmats[:, 1:],
        out.rotmats[:, 0],
        transl,
        vertex_ids=vertex_ids if (want_gaussians or not with_vertices) else None,
        return_transforms=want_gaussians,
    )
    pred = BodyPrediction(
        rotmats=out.rotmats,
        betas=out.betas,
        transl_cam=transl,
        joints_cam=body_out.joints,
        vertices_cam=body_out.vertices if (with_vertices or want_gaussians) else None,
    )
    if body_out.joint_transforms is not None:
        pred.joint_rotations_cam = body_out.joint_transforms[..., :3, :3]
    if want_gaussians:
        pred.gaussian_params = out.gaussians
        pred.gaussians_cam = pose_gaussians(
            out.gaussians, body_out.vertices, body_out.vertex_transforms
        )
    if R_in is not None and t_in is not None:
        pred.joints_world = to_world(pred.joints_cam, R_in, t_in)
        if pred.gaussians_cam is not None:
            pred.gaussians_world = _gaussians_to_world(pred.gaussians_cam, R_in, t_in)
    return pred
