"""Where each BlazePose landmark truly is in a crop: the virtual markers of the true body
(`gst.body.markers.MarkerModel`) projected with the crop's K, R, t, with the truth's visibility
of each marker's anchor joint (in the image, not behind anything).

A facing test for markers away from their joint (the nose seen from behind) was tried and
dropped: BlazePose gives the face landmarks high confidence from behind as well (measured:
2.5% dropped), so the anchor's visibility is the better predictor of what it reports.
"""

from __future__ import annotations

import numpy as np
import torch

from gst.body import BodyModel
from gst.body.markers import MarkerModel
from gst.body.model import BodyOutput


def project(points_world: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor):
    """(B, M, 3) world points -> (B, M, 2) crop pixels and (B, M) depth."""
    cam = points_world @ R.transpose(1, 2) + t[:, None]
    z = cam[..., 2]
    uv = cam[..., :2] / z[..., None].clamp_min(1e-6) @ K[:, :2, :2].transpose(1, 2)
    return uv + K[:, None, :2, 2], z


def marker_references(
    markers: MarkerModel,
    out: BodyOutput,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    joint_visible: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Markers of a posed body (world frame, `return_transforms=True`) in the crops:
    (B, M, 2) crop px and (B, M) bool visibility (the anchor joint's)."""
    pos = markers.positions(out)
    uv, z = project(pos, K, R, t)
    anchors = markers.anchors.to(joint_visible.device)
    return uv, joint_visible.bool()[:, anchors] & (z > 0)


def truth_body(body: BodyModel, betas, body_pose, global_orient, transl, batch: int = 512):
    """Pose the truth's parameters (numpy, world frame) with joint transforms, in batches."""
    outs = []
    dt = body.dtype
    for i in range(0, len(betas), batch):
        sl = slice(i, i + batch)
        b = torch.as_tensor(np.asarray(betas[sl]), dtype=dt)[:, : body.num_betas]
        outs.append(
            body(
                b,
                torch.as_tensor(np.asarray(body_pose[sl]), dtype=dt).reshape(len(b), 23, 3),
                torch.as_tensor(np.asarray(global_orient[sl]), dtype=dt),
                torch.as_tensor(np.asarray(transl[sl]), dtype=dt),
                vertex_ids=torch.zeros(1, dtype=torch.long),
                return_transforms=True,
            )
        )
    return BodyOutput(
        vertices=torch.cat([o.vertices for o in outs]),
        joints=torch.cat([o.joints for o in outs]),
        joint_transforms=torch.cat([o.joint_transforms for o in outs]),
    )


def world_references(world, body: BodyModel, markers: MarkerModel | None = None):
    """Marker references of a `gst.lift.dataset.LandmarkWorld`'s crops (numpy):
    (N, 33, 2) crop px and (N, 33) bool."""
    markers = markers or MarkerModel.load()
    out = truth_body(body, world.betas, world.body_pose, world.global_orient, world.transl)
    f = out.joints.dtype
    uv, vis = marker_references(
        markers,
        out,
        torch.as_tensor(world.K_crop, dtype=f),
        torch.as_tensor(world.R, dtype=f),
        torch.as_tensor(world.t, dtype=f),
        torch.as_tensor(world.visible),
    )
    return uv.numpy(), vis.numpy()
