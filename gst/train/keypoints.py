"""Detected 2D joints of every crop, for a label-free reprojection term in multi-view training.

The BlazePose landmark model (gst.detect) looks at each crop as one region of interest (the
crop frames the person with margin, as the model expects) and gives 33 landmarks with a
visibility each. Thirteen of the body model's 24 joints have a counterpart: the hips, knees,
ankles, shoulders, elbows and wrists, and the pelvis as the mid-point of the hips. Each such
joint gets its crop-pixel position and a confidence (presence x visibility); the others get
confidence 0.

`keypoint_term` projects the predicted world points (the landmarks' virtual markers on the
body, `marker_keypoints`; the joints where no marker table is given) into every target view of
a multi-view batch and compares them with those views' detections: the 2D evidence of several
calibrated cameras constrains the 3D joints, which the photometric terms alone do not pull in
from a poor start. Ours, not the paper's (weight `losses.keypoints`, 0 gives its objective);
no 3D labels are used, and held-out cameras never enter training batches.
"""

from __future__ import annotations

import numpy as np
import torch

from gst.detect.blazepose import BlazePose
from gst.detect.crops import detect_crop_landmarks

# body-model joint (SMPL order) -> BlazePose landmarks averaged for it
BODY_FROM_BLAZEPOSE: dict[int, tuple[int, ...]] = {
    0: (23, 24),  # pelvis: mid-hips
    1: (23,),
    2: (24,),  # hips
    4: (25,),
    5: (26,),  # knees
    7: (27,),
    8: (28,),  # ankles
    16: (11,),
    17: (12,),  # shoulders
    18: (13,),
    19: (14,),  # elbows
    20: (15,),
    21: (16,),  # wrists
}


def keypoints_from_landmarks(landmarks: torch.Tensor) -> torch.Tensor:
    """(N, 33, 3) crop landmarks (u, v, confidence = visibility x presence; NaN: none) ->
    (N, 24, 3) joints (u, v, confidence): each joint is the mean of its landmarks
    (BODY_FROM_BLAZEPOSE), with their least confidence; unmapped joints stay 0."""
    lm = torch.nan_to_num(torch.as_tensor(landmarks, dtype=torch.float32), nan=0.0)
    out = torch.zeros(lm.shape[0], 24, 3)
    for j, src in BODY_FROM_BLAZEPOSE.items():
        pts = lm[:, list(src)]
        out[:, j, :2] = pts[..., :2].mean(1)
        out[:, j, 2] = pts[..., 2].amin(1)
    return out


def store_landmarks(
    store_path,
    images: torch.Tensor,
    model: BlazePose | None = None,
    progress=None,
    reread: np.ndarray | None = None,
) -> tuple[torch.Tensor, str]:
    """(N, 33, 3) landmarks of a crop store's rows, in order (u, v crop px, confidence = the
    landmark's visibility, the scale of the store's and of tracking's landmarks; the whole
    crop's presence is not folded in, which on a crop read whole lowered some rows' confidences
    by up to 0.6): the store's `landmarks` dataset when the extraction wrote one, else BlazePose
    on the crops (`images`, the store's rows as RGB). Returns them and their source.

    `reread` (N,) bool: rows that are scored as single images (held-out frames or cameras).
    Where the store's landmarks of such a row were projected from the rig's skeleton (the
    extraction's model found nobody there who fitted), they hold what every camera saw, the
    held-out ones included: those rows get BlazePose's own reading of the crop instead, as a
    single image gives it."""
    from gst.data.store import CropStore

    store = CropStore(store_path)
    try:
        stored = store.read_landmarks()
    finally:
        store.close()
    if stored is not None and len(stored) == len(images):
        projected = projected_rows(store_path, len(images)) if reread is not None else None
        if projected is None:
            return torch.from_numpy(stored), "store"
        again = projected & np.asarray(reread, bool)
        if again.any():
            found = detect_crop_landmarks(images[torch.from_numpy(again)].numpy(), model, rgb=True)
            stored[again] = found.landmarks.astype(np.float32)
        return torch.from_numpy(stored), f"store ({int(again.sum())} projected read again)"
    found = detect_crop_landmarks(images.numpy(), model, rgb=True, progress=progress)
    return torch.from_numpy(found.landmarks.astype(np.float32)), "BlazePose"


def projected_rows(store_path, n: int) -> np.ndarray | None:
    """(n,) bool: the store's rows whose landmarks the extraction projected from the rig's
    skeleton (None when the store does not say or holds another number of rows)."""
    from gst.data.store import CropStore

    store = CropStore(store_path)
    try:
        projected = store.read_landmarks_projected()
    finally:
        store.close()
    return None if projected is None or len(projected) != n else np.asarray(projected, bool)


def marker_keypoints(
    joints_world: torch.Tensor,
    rotations_cam: torch.Tensor,
    R_in: torch.Tensor,
    markers,
) -> torch.Tensor:
    """(B, 24, 3) world points to compare with the detected joints of `keypoints_from_landmarks`:
    for each mapped joint the mean of its landmarks' virtual markers on the predicted body
    (gst.body.markers: BlazePose's hip is not the body model's hip joint; the landmarks put
    the pelvis 25 mm low, the hips 39 mm narrow and the shoulders 20-30 mm high against the
    joints), the other joints as they are. `rotations_cam` (B, 24, 3, 3) the joints' frames in
    the input camera (BodyPrediction.joint_rotations_cam), `R_in` (B, 3, 3) its
    world-to-camera rotation, `markers` a gst.body.markers.MarkerModel."""
    # the joints' frames in the world: R_in maps world to camera axes
    rotations_world = R_in.to(rotations_cam).transpose(1, 2)[:, None] @ rotations_cam
    at = markers.at(joints_world, rotations_world)  # (B, M, 3) world
    out = joints_world.clone()
    for j, src in BODY_FROM_BLAZEPOSE.items():
        out[:, j] = at[:, list(src)].mean(1)
    return out


def keypoint_term(
    joints_world: torch.Tensor,
    viewmats: torch.Tensor,
    K: torch.Tensor,
    keypoints: torch.Tensor,
    image_size: int,
) -> torch.Tensor:
    """Confidence-weighted mean distance, in image widths, between the predicted joints
    (B, J, 3) projected into the target views (viewmats (B, M, 4, 4), K (B, M, 3, 3)) and
    the views' detected joints (B, M, J, 3: u, v, confidence, in the same pixels as K).

    Computed in float32 with autocast off: under bf16 autocast (TrainConfig.amp) the einsums ran
    in bf16, which puts world points a few metres out about a centimetre off and the projections
    a fifth of a pixel (at 64 px) off, a noise floor of the term's own size."""
    with torch.autocast(joints_world.device.type, enabled=False):
        joints_world, viewmats, K = joints_world.float(), viewmats.float(), K.float()
        keypoints = keypoints.float()
        R, t = viewmats[..., :3, :3], viewmats[..., :3, 3]
        cam = torch.einsum("bmij,bnj->bmni", R, joints_world) + t[:, :, None, :]
        z = cam[..., 2:].clamp_min(1e-3)
        uv = torch.einsum("bmij,bmnj->bmni", K, cam / z)[..., :2]
        conf = keypoints[..., 2] * (cam[..., 2] > 1e-3)
        err = (uv - keypoints[..., :2]).norm(dim=-1) / image_size
        return (conf * err.clamp(max=0.5)).sum() / conf.sum().clamp_min(1e-6)
