"""Person crops cut again from the fitted bodies (the fuse stage's `bodycrops/`,
`gst.fuse.rounds`; docs/fuse.md "Crops from the fitted bodies", docs/formats/crops_h5.md).

The extraction decides in each view which pixels are whose from 2D evidence and per-frame
skeletons; in crowds it gives views to the wrong person, splits ids and misses people whom
others hide. After `fuse` every person has one body fitted over the clip from all cameras.
Projected into each camera (`gst.fuse.body_labels`), the bodies share the image's foreground
among them by whose surface is in front, and each person's crop is cut again with that mask
(`gst.data.extract.crops.crop_person`, the extraction's conventions). Ids are the fused ids, the
same in every camera, and every fitted person-frame gets a crop in every camera that sees some
of them.

Foreground: the extraction's background model (same settings, learnt from the same clean plates
or from the video itself) united with the extraction's person masks of the view, which cover
the people a background model cannot see (people who stand still).

Landmarks: a new crop takes those of the extraction's crop in the same view whose mask it
overlaps most (one to one, IoU at least `min_landmark_iou`), re-expressed in the new crop's
pixels; a crop that no extraction crop matches has none (confidence 0, `landmarks_projected`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from calibration.camera import FRAME_PADDING_TOLERANCE, Camera, Rig, fit_to_frames
from gst.atomic import atomic_path, atomic_write_text
from gst.body import load_body_model
from gst.cores import available_cores
from gst.data.background import BackgroundConfig, build_background, sample_indices
from gst.data.evaluate import CropTruth, association_accuracy
from gst.data.external import IdMaskFile
from gst.data.extract.crops import crop_person, score_against_truth, visible_truth_views
from gst.data.extract.options import WORK_MAX_SIDE
from gst.data.masks import MaskConfig, clean_mask
from gst.data.report import contact_sheet
from gst.data.store import CropBatch, CropStore, CropStoreWriter, index_path_for
from gst.fuse.body_labels import CameraRays, body_labels
from gst.fuse.tables import FusedBodies, read_fused_bodies
from gst.track.writer import settings_digest
from gst.video import held_frames, probe_video, read_frames, scaled_size
from synth.render import RayCaster
from synth.truth import truth_mask_file

__all__ = [
    "BodyCropOptions",
    "BodyCropReport",
    "lenders",
    "move_landmarks",
    "recut_crops",
    "write_body_crop_report",
]


@dataclass(frozen=True)
class BodyCropOptions:
    # foreground this far (working pixels) from every body's silhouette is nobody's; on the
    # crowd scenes 2 px gave 0.79 and 8 px 0.81 mean IoU, 8 px the same as no limit
    max_distance_px: float = 8.0
    min_pixels: int = 20  # a person's visible area below this (working pixels): no crop
    min_landmark_iou: float = 0.3  # an extraction crop lends its landmarks above this overlap
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    work_max_side: int = WORK_MAX_SIDE  # the extraction's working size (longer side, px)
    frame_size_tolerance: int = FRAME_PADDING_TOLERANCE  # calibration.camera.fit_to_frames


@dataclass
class BodyCropReport:
    crops: int
    people: int
    frames: int
    crops_per_camera: dict[str, int]
    with_landmarks: int  # crops that took the landmarks of an extraction crop
    seconds: float
    # synthetic scenes (truth ids): as the extraction's report counts them
    mask_iou: float | None = None
    association_accuracy: float | None = None
    visible_views: int = 0  # truth views with >= 30 % of the person's joints visible
    visible_views_missed: int = 0  # ... of which no crop shows that person
    # how far the bodies' crops differ from the extraction's: the extraction's crops (in every
    # frame, those where nobody was fitted too), how many of the cut's crops were paired one to
    # one with one of them (`lenders`, IoU >= min_landmark_iou) and the pairs' mean mask IoU
    extraction_crops: int = 0
    paired: int = 0
    paired_mean_iou: float | None = None
    unposed: int = 0  # rows of the bodies file with non-finite parameters (a failed fit): no crop

    def agreement(self) -> float:
        """Pairs over the crops of either side (1: every crop of both has its partner; two
        empty sides agree, so a scene without people ends its rounds at once)."""
        if self.crops == 0 and self.extraction_crops == 0:
            return 1.0
        return self.paired / max(self.crops, self.extraction_crops)

    def summary_line(self) -> str:
        line = (
            f"{self.crops} crops of {self.people} people over {self.frames} frames cut from the "
            f"fitted bodies ({self.with_landmarks} with the extraction's landmarks) in "
            f"{self.seconds:.1f} s; {self.paired} paired one to one with the extraction's "
            f"{self.extraction_crops} (agreement {self.agreement():.3f}"
            + (f", mask IoU {self.paired_mean_iou:.3f})" if self.paired_mean_iou is not None
               else ")")
        )  # fmt: skip
        if self.unposed:
            line += f"; {self.unposed} fitted body with non-finite parameters left out"
        if self.mask_iou is not None:
            missed = self.visible_views_missed / max(self.visible_views, 1)
            line += (
                f"; truth: mask IoU {self.mask_iou:.3f}, association "
                f"{self.association_accuracy:.3f}, missed {self.visible_views_missed} of "
                f"{self.visible_views} views >= 30 % visible ({missed:.3f})"
            )
        return line

    def as_dict(self) -> dict:
        return {**asdict(self), "agreement": self.agreement()}


class _CameraSource:
    """One camera's input: its rays, background model, extraction crops and truth."""

    def __init__(self, camera: Camera, fitted: Camera, index: int, video: Path,
                 plate: Path | None, source, options: BodyCropOptions,
                 truth_dir: Path | None):  # fmt: skip
        info = probe_video(video, camera.name, strict=True)
        tol = options.frame_size_tolerance

        def framed(cam: Camera) -> Camera:  # the extraction's fit to these frames (padding)
            return fit_to_frames(cam, info.width, info.height, tol, str(video))[0]

        # crops keep the calibration's camera (as the extraction's); the bodies are projected
        # with the camera they were fitted in
        camera = framed(camera)
        self.camera, self.index, self.video = camera, index, video
        s = min(1.0, options.work_max_side / max(camera.width, camera.height))
        self.size = scaled_size(camera.width, camera.height, s)
        self.rays = CameraRays(framed(fitted), self.size)
        clip = plate if plate is not None else video
        # the frames the clip holds (a container that announces one or two more failed here as
        # "truncated or corrupt", after the extraction had read it: gst.video.held_frames)
        n = held_frames(info if plate is None else probe_video(plate, camera.name, strict=True))
        idx = sample_indices(n, options.background.samples)
        samples = np.stack([img for _, img in read_frames(clip, idx, camera.name, size=self.size)])
        self.background = build_background(samples, options.background)
        self.rows = source.select(cameras=[camera.name])
        self.frame_of_row = source.index.column("frame").to_numpy()[self.rows]
        self.truth = IdMaskFile(truth_mask_file(truth_dir, camera.name)) if truth_dir else None

    def _work(self, image: np.ndarray) -> np.ndarray:
        if image.shape[1::-1] == self.size:
            return image
        return cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)

    def foreground(self, image: np.ndarray, extraction_masks: list[np.ndarray], o) -> np.ndarray:
        fg = clean_mask(self.background.foreground(self._work(image)), o.masks)[0] > 0
        for m in extraction_masks:
            fg |= m
        return fg

    def extraction_masks(
        self, source: CropStore, frame: int
    ) -> tuple[np.ndarray, np.ndarray, list]:
        """The extraction's crops of this view: their rows, `K_crop`s and masks at working size."""
        rows = self.rows[self.frame_of_row == frame]
        K_crop = source.read_column("K_crop", rows) if len(rows) else np.zeros((0, 3, 3))
        masks = []
        if len(rows):
            xy = self.rays.xy
            for m, K in zip(source.read_masks(rows), K_crop, strict=True):
                mx = (K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]).astype(np.float32)
                my = (K[1, 1] * xy[..., 1] + K[1, 2]).astype(np.float32)
                masks.append(cv2.remap(m, mx, my, cv2.INTER_LINEAR, borderValue=0) >= 128)
        return rows, K_crop, masks


def move_landmarks(lm: np.ndarray, K_from: np.ndarray, K_to: np.ndarray) -> np.ndarray:
    """(33, 3) crop landmarks of one crop re-expressed in another crop of the same view."""
    out = np.zeros_like(lm)
    ok = lm[:, 2] > 0
    if ok.any():
        uvw = np.c_[lm[ok, :2], np.ones(ok.sum())] @ (K_to @ np.linalg.inv(K_from)).T
        out[ok, :2] = uvw[:, :2] / uvw[:, 2:3]
        out[ok, 2] = lm[ok, 2]
    return out


def lenders(
    new: list[np.ndarray], old: list[np.ndarray], min_iou: float
) -> dict[int, tuple[int, float]]:
    """One-to-one by IoU (Hungarian), pairs of at least `min_iou`: new mask index ->
    (extraction mask index, the pair's IoU)."""
    if not new or not old:
        return {}
    iou = np.array([[_iou(a, b) for b in old] for a in new])
    a, b = linear_sum_assignment(-iou)
    return {
        int(i): (int(j), float(iou[i, j]))
        for i, j in zip(a, b, strict=True)
        if iou[i, j] >= min_iou
    }


def _finite_bodies(bodies: FusedBodies) -> tuple[FusedBodies, int]:
    """The rows whose body parameters are finite, and how many were not. A fit that failed
    leaves NaN parameters: the body model refuses the frame's whole batch (naming no person or
    frame), so such a row is a person not fitted in that frame (its views get no crop)."""
    params = (bodies.betas, bodies.body_pose, bodies.global_orient, bodies.transl)
    if not len(bodies):
        return bodies, 0
    ok = np.all([np.isfinite(a).reshape(len(bodies), -1).all(1) for a in params], axis=0)
    if ok.all():
        return bodies, 0
    return bodies.select(ok), int(np.count_nonzero(~ok))


@torch.no_grad()
def _frame_vertices(body, bodies: FusedBodies, rows: np.ndarray) -> list[np.ndarray]:
    """World vertices (V, 3) of the fitted bodies in `rows`."""
    params = (bodies.betas, bodies.body_pose, bodies.global_orient, bodies.transl)
    out = body(*(torch.as_tensor(a[rows], dtype=body.dtype) for a in params))
    return list(out.vertices.float().numpy())


def recut_crops(
    crops_h5: Path,
    rig: Rig,
    videos: dict[str, Path],
    bodies_parquet: Path,
    out_h5: Path,
    *,
    plates: dict[str, Path] | None = None,
    fitted_rig: Rig | None = None,
    options: BodyCropOptions = BodyCropOptions(),
    truth_dir: Path | None = None,
    progress: Callable | None = None,
    threads: int | None = None,
) -> BodyCropReport:
    """Cut every fitted person's crop in every camera again from the fitted bodies (module
    doc) into a new crop store `out_h5`. `crops_h5` is the extraction's store (its settings,
    masks and landmarks), `videos` and `plates` (clean plates; None: the background is learnt
    from each video, as the extraction does) are per camera, `truth_dir` a synthetic scene's
    folder for the truth figures. `fitted_rig`: the cameras the bodies were fitted in
    (`FuseResult.rig`, rotations corrected by the fit), to project the bodies with; the crops
    keep `rig`'s cameras, as the extraction's do (default: `rig` for both). The cameras of a
    frame are cut on `threads` threads (default: the cores)."""
    t0 = time.perf_counter()
    source = CropStore(crops_h5)
    bodies, unposed = _finite_bodies(read_fused_bodies(bodies_parquet))
    names = source.camera_names
    missing = [n for n in names if n not in videos or n not in rig.names]
    if missing:
        raise ValueError(
            f"{crops_h5}: cameras {missing} have no video or no calibration (videos: "
            f"{sorted(videos)}, rig: {rig.names})"
        )
    body = load_body_model(bodies.body_model)
    frames = np.unique(bodies.frame)
    visible: dict[tuple[str, int], set[int]] | None = None
    if truth_dir is not None:
        visible = {}
        for name, views in visible_truth_views(truth_dir, names).items():
            for f, p in views:
                visible.setdefault((name, f), set()).add(p)
    S = source.crop_size
    scale = float(source.attrs.get("setting.scale", 1.2))
    lm_source = source.read_landmarks(np.zeros(0, np.int64)) is not None
    settings = {
        "scale": scale,
        "frame_stride": int(source.attrs.get("setting.frame_stride", 1)),
        "method": str(source.attrs.get("setting.method", "")),  # the extraction's, as it wrote it
        "association": "bodies",
        "config": settings_digest({"options": _as_json(options), "source": str(crops_h5.name)}),
    }
    report = BodyCropReport(0, len(np.unique(bodies.person_id)), len(frames),
                            {n: 0 for n in names}, 0, 0.0, unposed=unposed)  # fmt: skip
    run = _Run(source, bodies, S, scale, options, lm_source)
    scored: list[CropTruth] = []
    out_h5.parent.mkdir(parents=True, exist_ok=True)
    for p in (out_h5, index_path_for(out_h5)):
        p.unlink(missing_ok=True)
    fitted = fitted_rig or rig
    # decoding, ray casting and OpenCV release Python's lock: the cameras run side by side
    with ThreadPoolExecutor(max(1, min(len(names), threads or available_cores()))) as pool:
        cams = list(pool.map(
            lambda i: _CameraSource(rig[names[i]], fitted[names[i]], i, Path(videos[names[i]]),
                                    (plates or {}).get(names[i]), source, options, truth_dir),
            range(len(names)),
        ))  # fmt: skip
        _cut_frames(cams, pool, body, frames, out_h5, settings, report, visible, scored, run,
                    progress)  # fmt: skip
    # the extraction's crops in frames where nobody was fitted pair with nothing
    report.extraction_crops += int(
        np.count_nonzero(~np.isin(source.index.column("frame").to_numpy(), frames))
    )
    if visible is not None:  # frames the extraction considered where nobody was fitted
        fitted = set(frames.tolist())
        considered = range(0, int(source.attrs.get("n_frames", 0)), settings["frame_stride"])
        for (_, f), want in visible.items():
            if f not in fitted and f in considered:
                report.visible_views += len(want)
                report.visible_views_missed += len(want)
    report.crops = sum(report.crops_per_camera.values())
    if scored:
        report.mask_iou = float(np.mean([r.iou for r in scored]))
        report.association_accuracy = association_accuracy(scored)[0]
    report.seconds = time.perf_counter() - t0
    return report


def _cut_frames(cams, pool, body, frames, out_h5, settings, report, visible, scored, run,
                progress) -> None:  # fmt: skip
    """Every fitted frame's crops, camera by camera on `pool`, into the store `out_h5`. The
    next frame's bodies are posed (and their ray-casting scene built) while this frame's views
    are cut."""
    source, bodies, S = run.source, run.bodies, run.crop_size
    names = [c.camera.name for c in cams]
    faces = np.asarray(body.faces, np.int32)
    readers = [iter(read_frames(c.video, frames.tolist(), c.camera.name)) for c in cams]

    def pose(f: int) -> tuple[np.ndarray, list, RayCaster]:
        rows = np.flatnonzero(bodies.frame == f)
        verts = _frame_vertices(body, bodies, rows)
        return rows, verts, RayCaster([(v, faces) for v in verts])

    def view(k: int, f: int, rows: np.ndarray, verts: list, caster: RayCaster):
        cam = cams[k]
        fi, image = next(readers[k])
        if fi != f:
            raise RuntimeError(f"{cam.video}: expected frame {f}, decoded {fi}")
        try:
            return _cut_view(run, cam, image, f, rows, verts, caster)
        except Exception as exc:  # raised on a pool thread: say which view
            exc.add_note(f"cutting camera {cam.camera.name}, frame {f} from the fitted bodies")
            raise

    steps = progress(frames, description="crops from the fitted bodies", total=len(frames)) \
        if progress else frames  # fmt: skip
    posed = pose(int(frames[0])) if len(frames) else None
    paired_iou = 0.0
    with CropStoreWriter(out_h5, names, S, settings, landmarks=run.landmarks) as writer:
        for i, f in enumerate(steps):
            f = int(f)
            views = [pool.submit(view, k, f, *posed) for k in range(len(cams))]
            posed = pose(int(frames[i + 1])) if i + 1 < len(frames) else None
            batches = []
            for cam, job in zip(cams, views, strict=True):
                cut = job.result()
                report.crops_per_camera[cam.camera.name] += len(cut.batch)
                report.with_landmarks += cut.lent
                report.extraction_crops += cut.extraction
                report.paired += cut.paired
                paired_iou += cut.paired_iou
                batches.append(cut.batch)
                scored += cut.truth
                if visible is not None:
                    want = visible.get((cam.camera.name, f), set())
                    report.visible_views += len(want)
                    report.visible_views_missed += len(want - {r.truth_id for r in cut.truth})
            writer.commit(CropBatch.concat(batches), [(f, c.index) for c in cams])
        if report.paired:
            report.paired_mean_iou = paired_iou / report.paired
        writer.finalize(
            {
                "source_videos": json.dumps({c.camera.name: c.video.name for c in cams}),
                "n_frames": int(source.attrs.get("n_frames", frames.max(initial=-1) + 1)),
            }
        )


@dataclass(frozen=True)
class _Run:
    """What every view of a run shares."""

    source: CropStore
    bodies: FusedBodies
    crop_size: int
    scale: float
    options: BodyCropOptions
    landmarks: bool  # the extraction's store holds landmarks (and so will this one)


@dataclass
class _ViewCut:
    """The crops of one camera and frame, and how they compare with the extraction's."""

    batch: CropBatch
    truth: list[CropTruth]  # synthetic scenes: each crop against the truth ids
    lent: int  # crops that took an extraction crop's landmarks
    extraction: int  # the extraction's crops of this view
    paired: int  # crops paired one to one with one of them (`lenders`)
    paired_iou: float  # the sum of the pairs' mask IoU


def _cut_view(
    run: _Run,
    cam: _CameraSource,
    image: np.ndarray,
    f: int,
    rows: np.ndarray,
    verts: list,
    caster: RayCaster,
) -> _ViewCut:
    """The crops of one camera and frame (module doc)."""
    o, source, S, lm_source = run.options, run.source, run.crop_size, run.landmarks
    old_rows, old_K, old_masks = cam.extraction_masks(source, f)
    fg = cam.foreground(image, old_masks, o)
    labels = body_labels(cam.rays, verts, caster, fg, o.max_distance_px)
    people = [k for k in range(len(rows)) if np.count_nonzero(labels == k) >= o.min_pixels]
    new_masks = [labels == k for k in people]
    pairs = lenders(new_masks, old_masks, o.min_landmark_iou)
    old_lm = source.read_landmarks(old_rows) if lm_source and len(old_rows) else None
    old_proj = source.read_landmarks_projected(old_rows) if old_lm is not None else None
    gt = cam.truth.get(f) if cam.truth is not None else None
    areas = np.bincount(gt.reshape(-1), minlength=256) if gt is not None else None
    parts, truth_rows, lent, written = [], [], 0, set()
    for i, (k, mask) in enumerate(zip(people, new_masks, strict=True)):
        got = crop_person(image, mask, cam.camera, S, run.scale)
        if got is None:
            continue
        written.add(i)
        img, msk, Kc, box, cbox = got
        r = rows[k]
        lm = proj = None
        if lm_source:
            j = pairs[i][0] if i in pairs else None
            lm = np.zeros((33, 3), np.float32)
            proj = True
            if j is not None:
                lent += 1
                lm = move_landmarks(old_lm[j], old_K[j], Kc).astype(np.float32)
                proj = bool(old_proj[j]) if old_proj is not None else False
        pid = int(run.bodies.person_id[r])
        parts.append(CropBatch(
            img[None], msk[None], Kc[None], cam.camera.R[None], cam.camera.t[None], box[None],
            cbox[None], np.array([cam.index], np.int32), np.array([f], np.int64),
            np.array([pid], np.int64), np.array([np.nan], np.float32),
            np.array([bool(run.bodies.single_view[r])]), None if lm is None else lm[None],
            None if proj is None else np.array([proj]),
        ))  # fmt: skip
        if gt is not None:
            tid, iou = score_against_truth(mask, gt, areas)
            truth_rows.append(CropTruth(f, cam.camera.name, pid, tid, iou, "body"))
    batch = CropBatch.concat(parts) if parts else CropBatch.empty(S, lm_source)
    ious = [iou for i, (_, iou) in pairs.items() if i in written]
    return _ViewCut(batch, truth_rows, lent, len(old_rows), len(ious), float(sum(ious)))


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 0.0


def _as_json(o: BodyCropOptions) -> dict:
    return json.loads(json.dumps(asdict(o), default=str))


def write_body_crop_report(report: BodyCropReport, store: Path, out_dir: Path) -> None:
    """`summary.json`, `report.md` and `contact_sheet.png` (crops with their masks) in
    `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "summary.json", json.dumps(report.as_dict(), indent=2) + "\n")
    lines = ["# Crops from the fitted bodies", "", f"- {report.summary_line()}", ""]
    lines += ["| camera | crops |", "| --- | ---: |"]
    lines += [f"| {n} | {c} |" for n, c in report.crops_per_camera.items()]
    lines += ["", "![contact sheet](contact_sheet.png)", ""]
    atomic_write_text(out_dir / "report.md", "\n".join(lines))
    with atomic_path(out_dir / "contact_sheet.png") as tmp:
        if not cv2.imwrite(str(tmp), contact_sheet(CropStore(store))):
            raise OSError(f"could not write {out_dir / 'contact_sheet.png'}")
