"""Per-crop pose errors and per-view novel-view scores of a GST model against exact truth.

Pose (one record per crop with truth): MPJPE (pelvis-aligned) and PA-MPJPE, per joint as well,
and vertex errors (PVE pelvis-aligned, PA-PVE) when truth meshes of the same topology are given.
Everything is compared in the world frame: predictions go through the input camera's pose.

Novel view (one record per (input crop, other view of the same person and frame)): the
prediction from the input crop is rendered into the other camera's crop, on black, and compared
with what that camera saw with the background removed (image x mask), as in SHERF/Neural Body:
- full crop: PSNR, SSIM, LPIPS and silhouette IoU over the whole rendered crop;
- SHERF-style ("box_*"): PSNR inside the truth body's projected 3D bounding box (padded 5 cm),
  SSIM and LPIPS on the crop to its 2D bounding rectangle (`gst.metrics.masked_bbox_metrics`).
Views from held-out cameras (never trained on) are flagged; the headline scores use only them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from gst.body.model import NonFiniteBatch
from gst.metrics.flips import mirrored_landmarks, reference_in_crops
from gst.metrics.image import masked_bbox_metrics, points_box_corners, psnr, silhouette_iou, ssim
from gst.metrics.pose import procrustes_align, vertex_error
from gst.model.assemble import to_world
from gst.train.evaluation import ViewPairs
from gst.train.occlusion import ignored_share, occluder_masks
from gst.train.steps import GSTTask, predict
from gst.train.views import CropSet, resize_images, target_views

__all__ = [
    "PoseRecords",
    "ViewRecords",
    "ViewPairs",
    "evaluate_pose",
    "evaluate_views",
    "view_pairs",
    "per_joint_errors",
]


def per_joint_errors(
    pred: torch.Tensor, gt: torch.Tensor, root: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, J) root-aligned and Procrustes-aligned per-joint distances of (B, J, 3) joints; their
    means over joints are MPJPE and PA-MPJPE. An item whose prediction is not finite gets NaN
    (counted, not averaged, by the summary; the SVD of one such item failed the whole call)."""
    rel = (pred - pred[:, root : root + 1]) - (gt - gt[:, root : root + 1])
    ok = torch.isfinite(pred).flatten(1).all(1)
    pa = torch.full_like(pred, float("nan"))
    if bool(ok.any()):
        pa[ok] = procrustes_align(pred[ok], gt[ok]) - gt[ok]
    return rel.norm(dim=-1), pa.norm(dim=-1)


def _predict_finite(model, task: GSTTask, crops: CropSet, rows: torch.Tensor, **kwargs):
    """`predict` on crops `rows`, leaving out the items whose network output is not finite (the
    body model refuses them: a diverged model, or one bad crop, ended the whole evaluation).
    Returns (prediction of rows[ok] or None, ok (B,) bool)."""
    ok = torch.ones(len(rows), dtype=torch.bool)
    while bool(ok.any()):
        r = rows[ok]
        try:
            pred = predict(
                model, task, crops.images[r], crops.K[r], crops.R[r], crops.t[r],
                landmarks=None if crops.landmarks is None else crops.landmarks[r], **kwargs,
            )  # fmt: skip
        except NonFiniteBatch as exc:
            ok[torch.nonzero(ok).flatten()[exc.rows]] = False
            continue
        return pred, ok
    return None, ok


@dataclass
class PoseRecords:
    """Per-crop pose errors in metres; `rows` index the evaluated CropSet."""

    rows: np.ndarray  # (N,)
    camera: np.ndarray  # (N,) camera index
    frame: np.ndarray  # (N,)
    joint_error: np.ndarray  # (N, 24) root-aligned
    joint_error_pa: np.ndarray  # (N, 24) after Procrustes
    pve: np.ndarray | None = None  # (N,) vertex error, pelvis-aligned
    pa_pve: np.ndarray | None = None  # (N,)
    # (N,) the crop's input landmarks are left/right mirrored against the reference
    # (gst.metrics.flips); None when the crops carry no landmarks
    mirrored: np.ndarray | None = None

    @property
    def mpjpe(self) -> np.ndarray:
        return self.joint_error.mean(1)

    @property
    def pa_mpjpe(self) -> np.ndarray:
        return self.joint_error_pa.mean(1)


@torch.no_grad()
def evaluate_pose(
    model,
    task: GSTTask,
    crops: CropSet,
    rows: torch.Tensor,
    scene_vertices: torch.Tensor | None = None,
    batch_size: int = 32,
) -> PoseRecords:
    """Pose errors of `model` on crops `rows` (which must have truth joints_world).

    `scene_vertices` (P, V, 3): truth world meshes indexed by crops.truth["truth_row"]; when
    given (and V matches the task's body model), vertex errors are computed too."""
    rows = torch.as_tensor(rows, dtype=torch.long)
    if "joints_world" not in crops.truth:
        raise ValueError(
            "evaluate_pose: the crop set has no truth joints_world (see gst.train.scene_truth)"
        )
    with_vertices = scene_vertices is not None
    if with_vertices:
        if "truth_row" not in crops.truth:
            raise ValueError(
                "evaluate_pose: scene_vertices given but the crop set has no truth_row"
            )
        if scene_vertices.shape[1] != task.body.num_vertices:
            raise ValueError(
                f"evaluate_pose: truth meshes have {scene_vertices.shape[1]} vertices, "
                f"the model's body {task.body.num_vertices}: vertex error needs the same topology"
            )
    je, jpa, pve, papve = [], [], [], []
    for s in range(0, len(rows), batch_size):
        r = rows[s : s + batch_size]
        pred, ok = _predict_finite(
            model, task, crops, r, with_gaussians=False, with_vertices=with_vertices
        )
        gt = crops.truth["joints_world"][r].float()
        joints = torch.full_like(gt, float("nan"))  # not finite: NaN errors, counted
        if pred is not None:
            joints[ok] = pred.joints_world.to(joints)
        e, pa = per_joint_errors(joints, gt)
        je.append(e)
        jpa.append(pa)
        if with_vertices:
            v_pve, v_pa = torch.full((len(r),), float("nan")), torch.full((len(r),), float("nan"))
            if pred is not None:
                ro, g = r[ok], gt[ok]
                v_pred = to_world(pred.vertices_cam, crops.R[ro], crops.t[ro])
                v_gt = scene_vertices[crops.truth["truth_row"][ro]].to(v_pred)
                # pelvis-aligned, as MPJPE: each mesh moves by its own root joint
                v_pve[ok] = vertex_error(
                    v_pred - pred.joints_world[:, :1], v_gt - g[:, :1].to(v_pred)
                ).to(v_pve)
                v_pa[ok] = vertex_error(v_pred, v_gt, align="procrustes").to(v_pa)
            pve.append(v_pve)
            papve.append(v_pa)
    cat = lambda xs: torch.cat(xs).double().numpy() if xs else np.zeros((0,))  # noqa: E731
    mirrored = None
    if crops.landmarks is not None:
        reference = reference_in_crops(
            crops.truth["joints_world"][rows], crops.R[rows], crops.t[rows], crops.K[rows]
        )
        mirrored = mirrored_landmarks(np.asarray(crops.landmarks[rows]), reference)
    return PoseRecords(
        rows=rows.numpy(),
        camera=crops.camera[rows].numpy(),
        frame=crops.frame[rows].numpy(),
        joint_error=cat(je).reshape(len(rows), -1),
        joint_error_pa=cat(jpa).reshape(len(rows), -1),
        pve=cat(pve) if with_vertices else None,
        pa_pve=cat(papve) if with_vertices else None,
        mirrored=mirrored,
    )


def view_pairs(
    crops: CropSet,
    heldout: set[int],
    rows: torch.Tensor | None = None,
    max_groups: int | None = None,
    seed: int = 0,
) -> ViewPairs:
    """For every (frame, person) seen by >= 2 cameras (among `rows`, default all): one input view,
    drawn from the training cameras (not `heldout`), and every other view as a target."""
    gen = torch.Generator().manual_seed(seed)
    allowed = torch.zeros(len(crops), dtype=torch.bool)
    allowed[
        torch.arange(len(crops)) if rows is None else torch.as_tensor(rows, dtype=torch.long)
    ] = True
    groups = [g[allowed[g]] for g in crops.groups(min_views=2)]
    groups = [
        g for g in groups if len(g) >= 2 and any(int(crops.camera[i]) not in heldout for i in g)
    ]
    if max_groups is not None and len(groups) > max_groups:
        keep = torch.randperm(len(groups), generator=gen)[:max_groups].sort().values
        groups = [groups[int(k)] for k in keep]
    inputs, targets = [], []
    for g in groups:
        train = [int(i) for i in g if int(crops.camera[i]) not in heldout]
        inp = train[int(torch.randint(len(train), (1,), generator=gen))]
        for i in g:
            if int(i) != inp:
                inputs.append(inp)
                targets.append(int(i))
    return ViewPairs(
        torch.tensor(inputs, dtype=torch.long), torch.tensor(targets, dtype=torch.long)
    )


@dataclass
class ViewRecords:
    """Per-pair novel-view scores. box_* are NaN where the body box is not visible."""

    inputs: np.ndarray
    targets: np.ndarray
    camera: np.ndarray  # target camera index
    heldout: np.ndarray  # bool: the target camera was never trained on
    psnr: np.ndarray
    ssim: np.ndarray
    lpips: np.ndarray  # NaN without an LPIPS model
    silhouette_iou: np.ndarray
    box_psnr: np.ndarray
    box_ssim: np.ndarray
    box_lpips: np.ndarray
    # the same with the target's pixels that another person covers left out (`occluder_masks`:
    # what is behind them is not known, and training leaves them out too)
    psnr_unoccluded: np.ndarray
    silhouette_iou_unoccluded: np.ndarray
    images: dict[int, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict
    )  # pair -> (render, target)


def _score_views(
    pred,
    crops: CropSet,
    inp,
    tgt,
    size: int,
    lpips,
    scene_vertices,
    box_margin: float,
    wanted: list[bool],
    occluders: torch.Tensor,
) -> dict[str, list]:
    """Scores of each (input, target) pair of one batch: per metric a list, and "images" the
    (render, target) uint8 pair of each `wanted` one (None for the others)."""
    from gst.render import rasterize

    nan = float("nan")
    cols: dict[str, list] = {}
    g = pred.gaussians_world
    view, K, image, mask = target_views(crops, tgt, size)
    target = image * mask[..., None]
    out = rasterize(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.colors,
        view[:, None],
        K[:, None],
        size,
        size,
        backgrounds=torch.zeros(len(inp), 1, 3),
    )
    rgb = out.rgb[:, 0].clamp(0, 1).permute(0, 3, 1, 2)
    tgt_img = target.permute(0, 3, 1, 2)
    cols["psnr"] = psnr(rgb, tgt_img).tolist()
    cols["ssim"] = ssim(rgb, tgt_img).tolist()
    cols["lpips"] = lpips(rgb, tgt_img).tolist() if lpips is not None else [nan] * len(inp)
    cols["iou"] = silhouette_iou(out.alpha[:, 0], mask).tolist()
    ignored = ignored_share(mask, resize_images(occluders[tgt][..., None], size)[..., 0])
    cols["psnr_unoccluded"] = psnr(rgb, tgt_img, mask=1 - ignored).tolist()
    cols["iou_unoccluded"] = silhouette_iou(out.alpha[:, 0], mask, ignore=ignored).tolist()
    row = crops.truth["truth_row"][tgt] if "truth_row" in crops.truth else None
    if sherf_box_kind(crops, scene_vertices) == "mesh":
        corners = np.stack(
            [points_box_corners(scene_vertices[int(k)].numpy(), box_margin) for k in row]
        )
    else:
        corners = np.stack(
            [
                points_box_corners(crops.truth["joints_world"][int(i)].numpy(), box_margin + 0.1)
                for i in tgt
            ]
        )
    box = masked_bbox_metrics(
        rgb,
        tgt_img,
        corners,
        K.numpy(),
        crops.R[tgt].numpy(),
        crops.t[tgt].numpy(),
        lpips=lpips,
    )
    cols["box_psnr"] = box.psnr.tolist()
    cols["box_ssim"] = box.ssim.tolist()
    cols["box_lpips"] = box.lpips.tolist() if box.lpips is not None else [nan] * len(inp)
    to8 = lambda x: (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)  # noqa: E731
    cols["images"] = [(to8(rgb[j]), to8(tgt_img[j])) if w else None for j, w in enumerate(wanted)]
    return cols


def sherf_box_kind(crops: CropSet, scene_vertices: torch.Tensor | None) -> str:
    """The box the SHERF-style scores use: "mesh", the truth body's (padded `box_margin`), or
    "joints", the reference joints' (padded 0.1 m more for the body's volume)."""
    return "mesh" if scene_vertices is not None and "truth_row" in crops.truth else "joints"


@torch.no_grad()
def evaluate_views(
    model,
    task: GSTTask,
    crops: CropSet,
    pairs: ViewPairs,
    heldout: set[int],
    size: int = 128,
    lpips=None,
    scene_vertices: torch.Tensor | None = None,
    box_margin: float = 0.05,
    batch_size: int = 16,
    keep_images: set[int] | None = None,
) -> ViewRecords:
    """Render each pair's prediction into its target view at `size` px and score it (module doc).

    SHERF-style box metrics need the truth mesh (`scene_vertices` indexed by truth_row); without
    it the box is that of the truth joints, padded by `box_margin` + 0.1 m for the body's volume.
    `keep_images`: pair indices whose (render, target) images to keep, uint8 (size, size, 3)."""

    nan = float("nan")
    keys = ("psnr", "ssim", "lpips", "iou", "box_psnr", "box_ssim", "box_lpips")
    cols: dict[str, list] = {k: [] for k in (*keys, "psnr_unoccluded", "iou_unoccluded")}
    occluders = crops.occluders if crops.occluders is not None else occluder_masks(crops)
    images: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    keep_images = keep_images or set()
    for s in range(0, len(pairs.inputs), batch_size):
        inp, tgt = pairs.inputs[s : s + batch_size], pairs.targets[s : s + batch_size]
        pred, ok = _predict_finite(model, task, crops, inp, with_gaussians=True)
        # an item whose prediction is not finite gets NaN scores (counted as such)
        wanted = [s + j in keep_images for j in range(len(inp)) if ok[j]]
        scored = (
            _score_views(
                pred,
                crops,
                inp[ok],
                tgt[ok],
                size,
                lpips,
                scene_vertices,
                box_margin,
                wanted,
                occluders,
            )
            if pred is not None
            else None
        )
        at = 0
        for j in range(len(inp)):
            if not ok[j]:
                for k in cols:
                    cols[k].append(nan)
                continue
            for k in cols:
                cols[k].append(scored[k][at])
            if s + j in keep_images:
                images[s + j] = scored["images"][at]
            at += 1
    cam = crops.camera[pairs.targets].numpy()
    arr = lambda k: np.asarray(cols[k], dtype=np.float64)  # noqa: E731
    return ViewRecords(
        inputs=pairs.inputs.numpy(),
        targets=pairs.targets.numpy(),
        camera=cam,
        heldout=np.isin(cam, sorted(heldout)),
        psnr=arr("psnr"),
        ssim=arr("ssim"),
        lpips=arr("lpips"),
        silhouette_iou=arr("iou"),
        box_psnr=arr("box_psnr"),
        box_ssim=arr("box_ssim"),
        box_lpips=arr("box_lpips"),
        psnr_unoccluded=arr("psnr_unoccluded"),
        silhouette_iou_unoccluded=arr("iou_unoccluded"),
        images=images,
    )
