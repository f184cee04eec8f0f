"""Multi-view crop sets in memory, and batch sampling for GST training.

A `CropSet` holds square person crops with their own intrinsics and extrinsics (crops are
undistorted, so K_crop, R, t describe them exactly) plus optional truth. `groups` lists, per
(frame, person), the crops of that person seen from different cameras: a training sample
takes one as the network input (chosen at random each time: the public GST code never
shuffled its input views) and renders into `num_targets` views: the input view itself and
others of the group (`sample_multiview`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from gst.train.distill_targets import DistillTargets

# optional fields with one row per crop (None: absent)
_PER_CROP_OPTIONAL = ("occluders", "anchors", "keypoints", "landmarks", "distill")


@dataclass
class CropSet:
    images: torch.Tensor  # (N, S, S, 3) uint8
    masks: torch.Tensor  # (N, S, S) float in [0, 1]
    K: torch.Tensor  # (N, 3, 3) crop intrinsics (OpenCV pixel centres)
    R: torch.Tensor  # (N, 3, 3) world-to-camera
    t: torch.Tensor  # (N, 3)
    camera: torch.Tensor  # (N,) index into camera_names
    frame: torch.Tensor  # (N,)
    person: torch.Tensor  # (N,)
    camera_names: list[str]
    truth: dict[str, torch.Tensor] = field(default_factory=dict)  # e.g. joints_world (N, 24, 3)
    occluders: torch.Tensor | None = None  # (N, S, S) other people's pixels (gst.train.occlusion)
    anchors: torch.Tensor | None = (
        None  # (N, 3) world point per crop, NaN if none (gst.train.anchors)
    )
    keypoints: torch.Tensor | None = (
        None  # (N, 24, 3) detected joints: crop px, confidence (gst.train.keypoints)
    )
    # (N, 33, 3) BlazePose landmarks: crop px, confidence (x presence); the input of landmark
    # tokens (gst.model.landmarks); NaN where none were detected
    landmarks: torch.Tensor | None = None
    # pseudo-3D targets from the rig's fused bodies, per crop (gst.train.distill)
    distill: DistillTargets | None = None

    def __post_init__(self):
        n = self.images.shape[0]
        for name in ("masks", "K", "R", "t", "camera", "frame", "person"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(
                    f"CropSet.{name} has {getattr(self, name).shape[0]} rows, images have {n}"
                )
        for name in _PER_CROP_OPTIONAL:
            self._check_rows(name, getattr(self, name))

    def __setattr__(self, name: str, value) -> None:
        # the optional per-crop fields are mostly attached after construction (prepare_crops):
        # one of another crop count was indexed by crop row in training, silently
        if name in _PER_CROP_OPTIONAL and "images" in self.__dict__:
            self._check_rows(name, value)
        super().__setattr__(name, value)

    def _check_rows(self, name: str, value) -> None:
        if value is not None and len(value) != len(self):
            raise ValueError(f"CropSet.{name} has {len(value)} rows, images have {len(self)}")

    @property
    def crop_size(self) -> int:
        return int(self.images.shape[1])

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def groups(self, cameras: set[int] | None = None, min_views: int = 2) -> list[torch.Tensor]:
        """Crop indices per (frame, person), restricted to `cameras`, with >= min_views views."""
        keep = torch.ones(len(self), dtype=torch.bool)
        if cameras is not None:
            keep = torch.isin(self.camera, torch.tensor(sorted(cameras)))
        idx = torch.nonzero(keep)[:, 0]
        # ids counted from the lowest: with frame * (max + 1) + id, id -1 in frame f had the key
        # of id max in frame f - 1 (two frames in one group); the order is the same as before
        low = int(self.person.min()) if len(self) else 0
        span = int(self.person.max()) - low + 1 if len(self) else 1
        key = self.frame[idx] * span + (self.person[idx] - low)
        order = torch.argsort(key, stable=True)
        idx, key = idx[order], key[order]
        _, counts = torch.unique_consecutive(key, return_counts=True)
        return [g for g in torch.split(idx, counts.tolist()) if len(g) >= min_views]


def heldout_frame_start(frames: torch.Tensor, fraction: float) -> int | None:
    """The first frame of the held-out time range: the last `fraction` of the distinct frames
    that have crops (None when `fraction` is 0). Training never sees frames from it on."""
    if not 0 <= fraction < 1:
        raise ValueError(f"the held-out share of frames must lie in [0, 1), got {fraction}")
    distinct = torch.unique(torch.as_tensor(frames))
    if fraction == 0 or len(distinct) == 0:
        return None
    if len(distinct) < 2:
        raise ValueError(f"holding out frames needs crops from >= 2 frames, got {len(distinct)}")
    n_test = max(1, round(fraction * len(distinct)))
    if n_test >= len(distinct):
        # 0.96 of 10 frames rounds to all ten: training then failed on "no training samples",
        # blaming the cameras
        raise ValueError(
            f"heldout_frames={fraction} holds out all {len(distinct)} frames that have crops; "
            f"a share below {(len(distinct) - 0.5) / len(distinct):.4g} leaves frames to train on"
        )
    return int(distinct[len(distinct) - n_test])


def concat_crop_sets(sets: list[CropSet], prefixes: list[str]) -> CropSet:
    """One CropSet from several worlds: camera names become '<prefix>/<name>', and frames are
    offset so (frame, person) groups of different worlds never merge. Truth keys must agree."""
    if not sets or len(sets) != len(prefixes):
        raise ValueError(
            f"concat_crop_sets needs one prefix per set, got {len(sets)} sets, "
            f"{len(prefixes)} prefixes"
        )
    keys = set(sets[0].truth)
    for prefix, s in zip(prefixes, sets, strict=True):
        if set(s.truth) != keys or s.crop_size != sets[0].crop_size:
            raise ValueError(
                f"crop set '{prefix}': truth keys {sorted(s.truth)} / crop size {s.crop_size} "
                f"differ from the first set's {sorted(keys)} / {sets[0].crop_size}"
            )
    cams, frames, names = [], [], []
    cam_offset = frame_offset = 0
    for prefix, s in zip(prefixes, sets, strict=True):
        cams.append(s.camera + cam_offset)
        frames.append(s.frame + frame_offset)
        names += [f"{prefix}/{n}" for n in s.camera_names]
        cam_offset += len(s.camera_names)
        frame_offset += int(s.frame.max()) + 1 if len(s) else 0

    def cat(name: str) -> torch.Tensor | None:
        parts = [getattr(s, name) for s in sets]
        if all(x is None for x in parts):
            return None
        if any(x is None for x in parts):
            raise ValueError(f"concat_crop_sets: some crop sets have {name}, others do not")
        return torch.cat(parts)

    return CropSet(
        images=cat("images"),
        masks=cat("masks"),
        K=cat("K"),
        R=cat("R"),
        t=cat("t"),
        camera=torch.cat(cams),
        frame=torch.cat(frames),
        person=cat("person"),
        camera_names=names,
        truth={k: torch.cat([s.truth[k] for s in sets]) for k in keys},
        occluders=cat("occluders"),
        anchors=cat("anchors"),
        keypoints=cat("keypoints"),
        landmarks=cat("landmarks"),
        distill=None
        if all(s.distill is None for s in sets)
        else DistillTargets.concat([s.distill for s in sets]),
    )


def scale_intrinsics(K: torch.Tensor, factor: float) -> torch.Tensor:
    """Intrinsics of an image resized by `factor`, with pixel centres at integers:
    u' = (u + 0.5) * factor - 0.5."""
    K2 = K.clone()
    K2[..., 0, :] = K[..., 0, :] * factor
    K2[..., 1, :] = K[..., 1, :] * factor
    K2[..., 0, 2] = (K[..., 0, 2] + 0.5) * factor - 0.5
    K2[..., 1, 2] = (K[..., 1, 2] + 0.5) * factor - 0.5
    return K2


def resize_images(images: torch.Tensor, size: int) -> torch.Tensor:
    """(..., S, S, C) float -> (..., size, size, C), area-averaged."""
    lead = images.shape[:-3]
    s, c = images.shape[-2], images.shape[-1]
    x = images.reshape(-1, s, s, c).permute(0, 3, 1, 2)
    if s != size:
        x = F.interpolate(x, size=(size, size), mode="area")
    return x.permute(0, 2, 3, 1).reshape(*lead, size, size, c)


def target_views(crops: CropSet, idx: torch.Tensor, size: int):
    """What rendering into crop rows `idx` (any shape) at `size` px needs: world-to-camera 4x4
    matrices, intrinsics scaled to `size`, images (float in [0, 1]) and masks resized to `size`."""
    view = torch.eye(4).repeat(*idx.shape, 1, 1)
    view[..., :3, :3] = crops.R[idx]
    view[..., :3, 3] = crops.t[idx]
    images = resize_images(crops.images[idx].float() / 255.0, size)
    masks = resize_images(crops.masks[idx][..., None].float(), size)[..., 0]
    return view, scale_intrinsics(crops.K[idx], size / crops.crop_size), images, masks


@dataclass
class MultiViewBatch:
    input_index: torch.Tensor  # (B,)
    target_index: torch.Tensor  # (B, M)
    input_images: torch.Tensor  # (B, S, S, 3) uint8
    K_in: torch.Tensor
    R_in: torch.Tensor
    t_in: torch.Tensor
    target_images: torch.Tensor  # (B, M, r, r, 3) float at render size
    target_masks: torch.Tensor  # (B, M, r, r)
    K_target: torch.Tensor  # (B, M, 3, 3) at render size
    viewmats: torch.Tensor  # (B, M, 4, 4)
    backgrounds: torch.Tensor  # (B, M, 3) random per view, so alpha must be right to match
    target_occluders: torch.Tensor | None = (
        None  # (B, M, r, r) other people's pixels: not supervised
    )
    anchors: torch.Tensor | None = (
        None  # (B, 3) the input person's triangulated mask centre (or NaN)
    )
    target_keypoints: torch.Tensor | None = (
        None  # (B, M, 24, 3) detected joints at render size, confidence
    )
    input_landmarks: torch.Tensor | None = None  # (B, 33, 3) the input crops' landmarks
    distill: DistillTargets | None = None  # the input crops' pseudo-3D targets


def sample_multiview(
    crops: CropSet,
    groups: list[torch.Tensor],
    gen: torch.Generator,
    batch_size: int,
    num_targets: int,
    render_size: int,
    include_input_view: bool = True,
    landmark_dropout: float = 0.0,
) -> MultiViewBatch:
    """Random groups; random input view per group; `num_targets` views to render into (the
    input view first when `include_input_view`, then others: every other view once before any
    repeats when there are too few; drawn with replacement, a view could be left out while
    another was rendered three times).
    `landmark_dropout`: share of samples whose input landmarks are hidden (NaN), so a landmark
    network keeps an image-only path for crops where the detector finds nothing."""
    pick = torch.randint(len(groups), (batch_size,), generator=gen)
    inputs, targets = [], []
    for gi in pick.tolist():
        g = groups[gi]
        perm = g[torch.randperm(len(g), generator=gen)]
        inp, others = perm[0], perm[1:]
        need = num_targets - int(include_input_view)
        if len(others) >= need:
            chosen = others[:need]
        else:
            extra = others[torch.randint(len(others), (need - len(others),), generator=gen)]
            chosen = torch.cat([others, extra])
        tgt = torch.cat([inp[None], chosen]) if include_input_view else chosen
        inputs.append(inp)
        targets.append(tgt)
    inp = torch.stack(inputs)
    tgt = torch.stack(targets)
    view, K, timg, tmask = target_views(crops, tgt, render_size)
    bg = torch.rand(*tgt.shape, 3, generator=gen)
    occ = (
        None
        if crops.occluders is None
        else resize_images(crops.occluders[tgt][..., None], render_size)[..., 0]
    )
    anchors = None if crops.anchors is None else crops.anchors[inp]
    keypoints = None
    if crops.keypoints is not None:  # crop pixels -> render pixels (pixel centres at integers)
        f = render_size / crops.crop_size
        keypoints = crops.keypoints[tgt].clone()
        keypoints[..., :2] = (keypoints[..., :2] + 0.5) * f - 0.5
    landmarks = None
    if crops.landmarks is not None:
        landmarks = crops.landmarks[inp].clone()
        if landmark_dropout > 0:
            drop = torch.rand(len(inp), generator=gen) < landmark_dropout
            landmarks[drop] = float("nan")
    return MultiViewBatch(
        inp,
        tgt,
        crops.images[inp],
        crops.K[inp],
        crops.R[inp],
        crops.t[inp],
        timg,
        tmask,
        K,
        view,
        bg,
        occ,
        anchors,
        keypoints,
        landmarks,
        None if crops.distill is None else crops.distill.take(inp),
    )


def load_cropset(store_path, rows=None) -> tuple[CropSet, np.ndarray]:
    """Read a crop store (gst.data.CropStore) into memory; returns the CropSet (RGB) and the
    person boxes (N, 4) in the undistorted full image."""
    from gst.data import CropStore

    store = CropStore(store_path)
    rows = np.arange(len(store)) if rows is None else np.asarray(rows)
    b = store.read(rows)
    crops = CropSet(
        images=torch.as_tensor(np.ascontiguousarray(b.rgb)),
        masks=torch.as_tensor(b.masks.astype(np.float32) / 255.0),
        K=torch.as_tensor(b.K_crop).float(),
        R=torch.as_tensor(b.R).float(),
        t=torch.as_tensor(b.t).float(),
        camera=torch.as_tensor(b.camera).long(),
        frame=torch.as_tensor(b.frame).long(),
        person=torch.as_tensor(b.person_id).long(),
        camera_names=list(store.camera_names),
    )
    return crops, b.box
