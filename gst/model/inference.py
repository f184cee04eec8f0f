"""Batched inference with a trained GST checkpoint.

`GSTPredictor(checkpoint).predict(crops, K_crop, landmarks=...)` returns a `BodyPrediction`
(pose, shape, camera-frame translation and joints, optional Gaussians); calling the predictor
returns plain numpy arrays in the layout `gst.track` consumes. The pose-only path skips the
Gaussian tokens exactly (the SMPL token never attends to them).

Landmarks: a checkpoint with landmark tokens (`GSTConfig.landmark_tokens`) also takes each
crop's 33 BlazePose landmarks, (B, 33, 3) = u, v in that crop's pixels (pixel centres at
integers, the pixels `K_crop` describes) and confidence (visibility x presence) in [0, 1];
NaN rows or points mean "not detected" and a crop without any takes the image-only path.
`GSTPredictor.accepts_landmarks` says whether the checkpoint uses them. A checkpoint built
with `GSTConfig.landmark_gravity` also reads `up`, (B, 3): the world's up direction in each
crop's camera frame (`gst.model.landmarks.camera_up` of the camera's rotation and the rig's up
axis) where the camera is calibrated; leave it out (or give zero rows) where it is not.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from gst.body import BodyModel, load_body_model
from gst.device import model_device
from gst.model.assemble import BodyPrediction, assemble
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.model.landmarks import LandmarkInput, landmark_input, select_landmarks
from gst.model.preprocess import check_crops, check_intrinsics, network_input, to_float_images

log = logging.getLogger("gst.model")


def _network_images(
    images: np.ndarray | torch.Tensor,
    image_size: tuple[int, int],
    device: torch.device,
    skip: torch.Tensor | None,
) -> torch.Tensor | None:
    """The network's input images, (B, 3, H, W); rows in `skip` (B,) bool stay zero, and None
    when every row is skipped (the network's landmark-only mode)."""
    if skip is None or not bool(skip.any()):
        if isinstance(images, torch.Tensor):
            images = images.to(device)  # uint8 travels, not its float copy
        return network_input(to_float_images(images).to(device), image_size)
    if bool(skip.all()):
        return None
    keep = torch.nonzero(~skip).flatten()
    rows = images[keep.numpy()] if isinstance(images, np.ndarray) else images[keep]
    some = network_input(to_float_images(rows).to(device), image_size)
    out = some.new_zeros((len(skip), *some.shape[1:]))
    out[keep.to(device)] = some
    return out


def predict_bodies(
    network: torch.nn.Module,
    body,
    vertex_ids: torch.Tensor,
    images: np.ndarray | torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    *,
    R: torch.Tensor | None = None,
    t: torch.Tensor | None = None,
    with_gaussians: bool = True,
    with_vertices: bool = False,
    crop_size: int | None = None,
    device: str | torch.device | None = None,
    landmarks: LandmarkInput | torch.Tensor | np.ndarray | None = None,
    up: torch.Tensor | np.ndarray | None = None,
    image_for_pose: bool = True,
) -> BodyPrediction:
    """The network on a batch of crops (B, S, S, 3) RGB uint8 or float images, assembled into
    posed bodies (and Gaussians) in the crops' cameras (K (B, 3, 3); optional input-camera R, t
    for world coordinates). `image_size` is the network's input size; `crop_size` the crops' side
    (default: the images' own). `landmarks`: the crops' BlazePose landmarks (B, 33, 3) (module
    doc) or a ready `gst.model.landmarks.LandmarkInput`; ignored by a network without landmark
    tokens, None gives the image-only path. `up` (B, 3): the world's up direction in the crops'
    cameras where calibrated (module doc). `image_for_pose` False: pose-only crops with landmarks
    skip the image path (`GSTNetwork.forward`). The one inference path of training, evaluation
    and tracking."""
    # inputs follow the network (a GPU-trained model validated on CPU crop stores, say)
    device = torch.device(device) if device is not None else model_device(network)
    images = check_crops(images)
    if len(images) == 0:  # the body model said "body_pose has an empty batch", or a reshape failed
        raise ValueError(
            "predict_bodies: an empty batch of crops (GSTPredictor.__call__ returns empty arrays "
            "for none)"
        )
    check_intrinsics(K, len(images))
    for name, value, shape in (("R", R, (3, 3)), ("t", t, (3,))):
        # one (3, 3) R for the batch failed deep in the assembly ("size of tensor a (24) ...")
        if value is not None and tuple(value.shape) != (len(images), *shape):
            raise ValueError(
                f"{name} must be ({len(images)}, {', '.join(map(str, shape))}): one per crop, "
                f"got {tuple(value.shape)}"
            )
    size = crop_size or images.shape[-2]
    if landmarks is not None and not isinstance(landmarks, LandmarkInput):
        landmarks = landmark_input(network, landmarks, K, size, up=up)
    if landmarks is not None:
        landmarks = landmarks.to(device)
    # Pose-only crops whose pose comes from their landmarks never read their pixels
    # (GSTNetwork.forward): converting and resizing them cost a tenth of tracking's network time.
    skip = None
    if landmarks is not None and not (image_for_pose or with_gaussians):
        skip = landmarks.has_landmarks.cpu()
    K = torch.as_tensor(K).to(device)
    R = None if R is None else torch.as_tensor(R).to(device)
    t = None if t is None else torch.as_tensor(t).to(device)
    extra = {} if landmarks is None else {"landmarks": landmarks}
    if not image_for_pose:
        extra["image_for_pose"] = False
    out = network(
        _network_images(images, image_size, device, skip), with_gaussians=with_gaussians, **extra
    )
    return assemble(
        out,
        body,
        K,
        size,
        vertex_ids=vertex_ids,
        R_in=R,
        t_in=t,
        with_vertices=with_vertices,
    )


# A landmark network whose SMPL token lets the image in by at most this factor in every decoder
# layer (`TokenDecoder.smpl_image_gate`, learnt in `train`) takes its pose from the landmarks:
# the image's share is negligible. Measured with the README demo's model (gate 0.021), skipping
# the image path for pose changed single-image MPJPE by at most 0.3 mm on the demo's held-out
# crops, the lab's 800 crops and two crowd scenes, at a quarter of the time per crop
# (docs/track_evaluation.md, "Pose from the landmarks").
NEGLIGIBLE_IMAGE_GATE = 0.05


def image_shapes_pose(network: torch.nn.Module) -> bool:
    """Whether the image path changes a landmark network's pose more than negligibly (always
    True for networks without landmark tokens or without an image gate)."""
    gate = getattr(getattr(network, "smpl_head", None), "transformer", None)
    gate = getattr(gate, "smpl_image_gate", None)
    if getattr(network, "landmark_encoder", None) is None or gate is None:
        return True
    return float(gate.detach().abs().max()) > NEGLIGIBLE_IMAGE_GATE


def _same_body(a: BodyModel, b: BodyModel) -> bool:
    """Whether two loaded body models are one body: layout, template, shape space, regressor."""
    da, db = a.data, b.data
    if (a.num_vertices, a.num_joints, a.num_betas) != (b.num_vertices, b.num_joints, b.num_betas):
        return False
    return all(
        np.allclose(x, y, rtol=0, atol=1e-6)
        for x, y in (
            (da.v_template, db.v_template),
            (da.shapedirs, db.shapedirs),
            (da.dense_J_regressor(), db.dense_J_regressor()),
        )
    )


def _checkpoint_body(ckpt, override: str | None, checkpoint, device) -> BodyModel:
    """The body the checkpoint's network was trained with: its own spec, or `override` (the same
    body found elsewhere, e.g. a user's SMPL file at another path). An override that is another
    body is refused: the network's shape coefficients, vertex ids and the refiner's skeleton are
    that body's, and another body gave plausible but wrong joints (0.4 m off) without a word."""
    own = override is None or override == ckpt.body_model
    spec = ckpt.body_model if own else override
    body = own_body(ckpt, checkpoint, device) if own else load_body_model(spec, device=device)
    # checked on both paths: the checkpoint's own spec may resolve to another body here (a path
    # holding another file since); it failed at the first batch, naming no file
    _check_vertex_ids(ckpt, body, f"{checkpoint}", f"body model {spec!r}")
    if not own:
        # an override is given on purpose: taken on trust when the checkpoint's body is gone
        check_same_body(ckpt, spec, lambda: body, f"{checkpoint}", "body_model", trust=True)
    return body


def own_body(ckpt, checkpoint, device=None) -> BodyModel:
    """The body model the checkpoint names, or a ValueError naming the checkpoint and what to do
    (a bare FileNotFoundError named the body's path alone: the checkpoint records it as given
    when training, an absolute path that moves with the project folder)."""
    try:
        return load_body_model(ckpt.body_model, device=device)
    except (FileNotFoundError, ValueError) as exc:
        raise ValueError(
            f"{checkpoint}: cannot load the body model its network was trained with, "
            f"{ckpt.body_model!r} ({exc}); the checkpoint records the body model as given to "
            "training: if that file moved (e.g. with the project folder), put it back or link "
            "it there, or give the same body at its new path where a body model is asked for "
            "(pretrain.body_model, train.body_model, GSTPredictor(body_model=...))"
        ) from None


def _is_file_spec(spec: str) -> bool:
    return spec != "anny" and spec != "smpl" and not spec.startswith("smpl:")


def _check_vertex_ids(ckpt, body: BodyModel, who: str, what: str) -> None:
    """The network's vertex ids must lie on `body` (`what` names it in the error)."""
    if len(ckpt.vertex_ids) and int(ckpt.vertex_ids.max()) >= body.num_vertices:
        raise ValueError(
            f"{who}: {what} has {body.num_vertices} vertices; the checkpoint's network (trained "
            f"with body model {ckpt.body_model!r}) uses vertex ids up to "
            f"{int(ckpt.vertex_ids.max())}: another body"
        )


def check_same_body(
    ckpt, spec: str, load_body, who: str, setting: str, *, trust: bool = False
) -> None:
    """That `spec` (a setting's body model; `load_body()` loads it) is the body the
    checkpoint's network was trained with: the same spec, or the same body by content (the same
    file at another path: a moved project folder). When the checkpoint's own body cannot be
    loaded here, `spec` is taken, with a warning, if the network's vertex ids fit it and either
    `trust` (a body given on purpose: GSTPredictor's override) or it is a file of the same name
    (a setting with a default, where another body may be an oversight: train, pretrain.reuse).
    `who` names the checkpoint in errors, `setting` the setting."""
    if spec == ckpt.body_model:
        return
    try:
        own = load_body_model(ckpt.body_model)
    except (FileNotFoundError, ValueError) as exc:
        moved = (
            _is_file_spec(spec)
            and _is_file_spec(ckpt.body_model)
            and Path(spec).name == Path(ckpt.body_model).name
        )
        if not (trust or moved):
            raise ValueError(
                f"{who} was trained with body model '{ckpt.body_model}', {setting} is '{spec}' "
                f"(the checkpoint's body cannot be loaded here to compare: {exc}); give "
                "the body it was trained with"
            ) from None
        _check_vertex_ids(ckpt, load_body(), who, f"{setting} '{spec}'")
        log.warning(
            "%s was trained with body model '%s', not found here (%s); taking %s '%s' as that "
            "body (it cannot be compared)",
            who, ckpt.body_model, exc, setting, spec,
        )  # fmt: skip
        return
    if not _same_body(own, load_body()):
        raise ValueError(
            f"{who} was trained with body model '{ckpt.body_model}', {setting} is '{spec}': "
            "not the body the network was trained with (another body: other size, template, "
            "shape space or joint regressor)"
        )
    log.info("%s: body model '%s' is its own, '%s'", who, spec, ckpt.body_model)


# How far (m) the body's rest skeleton, or a unit of each shape coefficient's move of it, may
# lie from the skeleton a network's refiner was trained on (float32 round-off is ~1e-7 m).
SKELETON_TOLERANCE_M = 1e-3


def check_body_fits_network(network: torch.nn.Module, body: BodyModel, checkpoint) -> None:
    """A network with a refiner (landmark networks: gst.model.refine) holds the skeleton of
    the body it was trained with. A body spec resolves on the machine that loads it ("smpl"
    through $GST_BODY_DIR or the cache; a path may hold another file since): another body with
    as many vertices gave joints some 0.1 m off without a word. Refused, with the distance.
    Networks without a refiner hold no skeleton: nothing to check."""
    refiner = getattr(network, "refiner", None)
    rest = getattr(refiner, "rest_joints", None)
    if rest is None or not bool(torch.isfinite(rest).all()):
        return
    shape = refiner.shape_joints
    nb = shape.shape[-1]
    if body.num_betas < nb:
        raise ValueError(
            f"{checkpoint}: the body has {body.num_betas} shape coefficients, the network was "
            f"trained with {nb}"
        )
    own_rest = body.J_template.detach().to("cpu", torch.float32)
    own_shape = body.J_shapedirs[..., :nb].detach().to("cpu", torch.float32)
    off = max(
        float((own_rest - rest.cpu()).abs().max()), float((own_shape - shape.cpu()).abs().max())
    )
    if off > SKELETON_TOLERANCE_M:
        raise ValueError(
            f"{checkpoint}: the body model it names resolves here to a body whose skeleton lies "
            f"up to {1000 * off:.1f} mm from the one the network was trained with (another "
            "file under the same name or path); pass the training body (`body_model`)"
        )


class GSTPredictor:
    """A checkpoint ready for inference. `image_path`: "auto" lets pose-only crops that have
    landmarks skip the image path when the network's image gate is negligible
    (`image_shapes_pose`; crops without landmarks and Gaussian outputs always use the image);
    "always" runs the image path for every crop."""

    def __init__(
        self,
        checkpoint: str | Path,
        *,
        with_gaussians: bool = False,
        device: str = "cpu",
        batch_size: int = 32,
        body_model: str | None = None,
        image_path: str = "auto",
    ):
        if image_path not in ("auto", "always"):
            raise ValueError(f"image_path must be 'auto' or 'always', got {image_path!r}")
        # built on the CPU (the checkpoint's arrays feed numpy), then moved
        ckpt = load_checkpoint(checkpoint, map_location="cpu")
        self.network = network_from_checkpoint(ckpt, checkpoint).to(device).eval()
        self.body = _checkpoint_body(ckpt, body_model, checkpoint, device)
        check_body_fits_network(self.network, self.body, checkpoint)
        self.vertex_ids = ckpt.vertex_ids.to(device)
        self.with_gaussians = with_gaussians
        self.device, self.batch_size = device, batch_size
        self.name = f"gst-{self.network.cfg.name}"
        self.checkpoint = str(checkpoint)
        self.pose_from_landmarks = image_path == "auto" and not image_shapes_pose(self.network)

    @property
    def accepts_landmarks(self) -> bool:
        """Whether the checkpoint's network has landmark tokens (then pass `landmarks=`)."""
        return self.network.landmark_encoder is not None

    @property
    def pose_input(self) -> str:
        """Where pose-only prediction takes the pose from: "landmarks" (crops with landmarks skip
        the image path; `image_path` auto and a negligible image gate), "image and landmarks",
        or "image" (a network without landmark tokens). With Gaussians the image is always read."""
        if self.pose_from_landmarks and not self.with_gaussians:
            return "landmarks"
        return "image and landmarks" if self.accepts_landmarks else "image"

    def needs_pixels(self, landmarks: np.ndarray | torch.Tensor) -> np.ndarray:
        """(B,) bool: whether pose-only prediction reads each crop's pixels, given the crops'
        (B, 33, 3) landmarks: False for crops whose pose comes from their landmarks alone
        (`image_path` auto, a negligible image gate, at least one landmark the network uses).
        A caller may hand those crops in blank (tracking skips cutting them)."""
        n = len(landmarks)
        if self.pose_input != "landmarks" or n == 0:
            return np.ones(n, bool)
        # LandmarkInput.has_landmarks in numpy (the tracking loop asks for every frame): a crop
        # has landmarks when one of the network's set is finite with a confidence above 0
        lm = select_landmarks(torch.as_tensor(landmarks), self.network.cfg.num_landmarks).numpy()
        usable = np.isfinite(lm).all(-1) & (np.nan_to_num(lm[..., 2]) > 0)
        return ~usable.any(1)

    @property
    def accepts_up(self) -> bool:
        """Whether the checkpoint's network reads the camera's up direction (then pass `up=`
        for calibrated cameras)."""
        return self.accepts_landmarks and self.network.cfg.landmark_gravity

    @torch.no_grad()
    def predict(
        self,
        crops: np.ndarray | torch.Tensor,
        K_crop: np.ndarray | torch.Tensor,
        R: torch.Tensor | None = None,
        t: torch.Tensor | None = None,
        with_gaussians: bool | None = None,
        landmarks: np.ndarray | torch.Tensor | None = None,
        up: np.ndarray | torch.Tensor | None = None,
    ) -> BodyPrediction:
        """One batch: crops (B, S, S, 3) RGB uint8, K_crop (B, 3, 3); optional input-camera R, t;
        `landmarks` (B, 33, 3) crop px + confidence, NaN where not detected; `up` (B, 3) the
        world's up in the crops' cameras where calibrated (module doc)."""
        want = self.with_gaussians if with_gaussians is None else with_gaussians
        K = torch.as_tensor(K_crop, dtype=torch.float32, device=self.device)
        if landmarks is not None and len(landmarks) != len(K):
            raise ValueError(f"{len(landmarks)} landmark rows for {len(K)} crops")
        return predict_bodies(
            self.network, self.body, self.vertex_ids, crops, K, self.network.cfg.image_size,
            R=R, t=t, with_gaussians=want, with_vertices=False, device=self.device,
            landmarks=landmarks, up=up, image_for_pose=not self.pose_from_landmarks,
        )  # fmt: skip

    def __call__(
        self,
        crops: np.ndarray,
        K_crop: np.ndarray,
        landmarks: np.ndarray | None = None,
        up: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Crops (N, S, S, 3) RGB uint8, K_crop (N, 3, 3) and, for a landmark checkpoint, the
        crops' landmarks (N, 33, 3) and, for calibrated cameras, the world's up in each crop's
        camera (N, 3) -> numpy arrays (the `gst.track.predictor` contract)."""
        parts = []
        for s in range(0, len(crops), self.batch_size):
            sl = slice(s, s + self.batch_size)
            pred = self.predict(
                crops[sl],
                K_crop[sl],
                landmarks=None if landmarks is None else landmarks[sl],
                up=None if up is None else up[sl],
            )
            part = {
                "rotmats": pred.rotmats,
                "betas": pred.betas[:, :10],
                "transl_cam": pred.transl_cam,
                "joints_cam": pred.joints_cam,
            }
            if pred.gaussians_cam is not None:  # camera-frame splat, handed to callers as extras
                g = pred.gaussians_cam
                part.update(
                    gaussian_means=g.means,
                    gaussian_quats=g.quats,
                    gaussian_scales=g.scales,
                    gaussian_opacities=g.opacities,
                    gaussian_colors=g.colors,
                )
            parts.append({k: v.detach().cpu().numpy().astype(np.float32) for k, v in part.items()})
        if not parts:
            return {
                "rotmats": np.zeros((0, 24, 3, 3), np.float32),
                "betas": np.zeros((0, 10), np.float32),
                "transl_cam": np.zeros((0, 3), np.float32),
                "joints_cam": np.zeros((0, 24, 3), np.float32),
            }
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
