"""`fuse_scene`: from a scene's crop store to world-space bodies, marker files and a report.

Steps: landmarks per crop (gst.fuse.observations) -> people regrouped by 3D agreement and
tracked (gst.fuse.regroup, with the per person-frame view consensus of gst.fuse.consensus:
views that show another person move to that person or are dropped, exchanged left/right limb
groups are put right) -> robust triangulation per person (gst.fuse.triangulate) -> body fit
over the clip (gst.fuse.fit), people in fixed batches -> outputs (docs/formats/fused_*.md):

    fused/bodies.parquet        the tracks schema in the world frame, + per-joint evidence
    fused/landmarks.parquet     triangulated BlazePose landmarks, views, errors, confidence
    fused/trc/person_<id>.trc   OpenSim markers (Y up), fused/c3d/person_<id>.c3d
    reports/fuse/               report.md, summary.json, bone_lengths.png, overlay/<camera>.mp4

Resumable: the landmarks and each batch of fits are saved under `fused/.work/` as they are
done (atomically); a rerun into the same folder with the same settings reuses them. Batches are
fixed by person order, so a resumed run writes the same bytes as an uninterrupted one. The
work folder is removed when everything is written.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from calibration.camera import Rig
from calibration.formats import rig_json
from gst.atomic import atomic_save_npz, atomic_write
from gst.body import load_body_model
from gst.body.markers import MarkerModel
from gst.cores import torch_threads
from gst.data.store import CropStore
from gst.fuse.consensus import (
    ConsensusOptions,
    exchange_groups,
    exchanges_against_body,
    readings_against_body,
)
from gst.fuse.consistency import per_frame_limb_lengths
from gst.fuse.export import write_c3d, write_trc
from gst.fuse.fit import FitOptions, PersonFit, fit_people
from gst.fuse.floor import scene_floor
from gst.fuse.observations import (
    READABLE_CONFIDENCE,
    READABLE_LANDMARKS,
    PersonObservations,
    crop_landmarks,
    group_by_person,
)
from gst.fuse.regroup import RegroupOptions, regroup_people
from gst.fuse.relook import RelookOptions, relook_crowded
from gst.fuse.report import FuseSummary, summarise, write_report
from gst.fuse.rig import apply_corrections, camera_corrections, corrected_rig, rotation_matrix
from gst.fuse.silhouettes import crop_silhouettes
from gst.fuse.spikes import drop_spikes
from gst.fuse.start import dense_triangulation
from gst.fuse.tables import joint_evidence, write_bodies, write_landmarks
from gst.fuse.triangulate import TriangulationOptions, triangulate_person

__all__ = ["FuseOptions", "FuseResult", "fuse_scene"]


@dataclass(frozen=True)
class FuseOptions:
    body_model: str = "anny"
    markers: str | None = None  # a markers JSON; None: the package's fitted table
    fit: FitOptions = FitOptions()
    # pair consensus over the 8 most confident views, the silhouettes and the neighbouring
    # frames voting (docs/fuse.md "Silhouettes")
    triangulation: TriangulationOptions = TriangulationOptions(
        consensus_views=8, temporal_weight=2.0
    )
    regroup: RegroupOptions | None = RegroupOptions()  # None: the extraction's people as they are
    refine_landmarks: bool = True  # second BlazePose pass (gst.detect.crops, refine=True)
    mask_others: bool = False  # dim pixels outside the crop's person mask before BlazePose
    # crops that other people crowd read again with those people painted over, the fitted body
    # choosing between the two readings of each (gst.fuse.relook; None: off)
    relook: RelookOptions | None = RelookOptions()
    refine_rig_rounds: int = (
        0  # rounds of camera rotations corrected from the bodies (gst.fuse.rig)
    )
    # rounds of limb groups exchanged left for right where the fitted body says a view read
    # them mirrored (gst.fuse.consensus.exchanges_against_body), each followed by a refit
    exchange_rounds: int = 1
    # the people's coverage of every view (gst.fuse.silhouettes): votes in the triangulation's
    # pair consensus (triangulation.consensus_views > 0) and the fit's term (fit.w_silhouette)
    silhouettes: bool = True
    # height of the floor along the rig's up axis, metres, that the fitted feet do not sink into;
    # "auto": 0 where the triangulated feet stand near it (gst.fuse.floor); None: no floor
    floor: float | Literal["auto"] | None = "auto"
    # a fitted marker this far (m, at 30 fps) from its neighbouring frames' midpoint is a
    # misreading: its landmarks in that frame are dropped and everyone refitted (gst.fuse.spikes)
    spike_m: float | None = 0.25
    spike_rounds: int = 1
    people_per_batch: int = 8  # people fitted together (fixed batches make resumes identical)
    overlay: bool = True
    # torch threads of the fit, for this call only (None: the process's; on 2 cores the fit runs
    # 1.5x faster on 2 than on 1, docs/fuse.md "What it measured")
    threads: int | None = None

    def settings(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), default=str))


@dataclass
class FuseResult:
    bodies: Path
    landmarks: Path
    trc: list[Path]
    c3d: list[Path]
    overlays: list[Path]
    summary: FuseSummary
    fits: list[PersonFit]
    rig: Rig  # the rig the bodies were fitted in (its rotations corrected with refine_rig_rounds)


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _landmarks_key(landmarks) -> str | None:
    """What identifies given landmarks in the resume key: an array's content digest; a reader
    function by its qualified name (its readings are cached in the work folder)."""
    if landmarks is None:
        return None
    if callable(landmarks):
        name = getattr(landmarks, "__qualname__", type(landmarks).__name__)
        return f"callable {getattr(landmarks, '__module__', '')}.{name}"
    a = np.ascontiguousarray(landmarks)
    return f"{a.dtype}{a.shape}" + hashlib.sha256(a.tobytes()).hexdigest()


def _video_fps(videos: dict[str, Path]) -> float:
    import cv2

    for path in videos.values():
        cap = cv2.VideoCapture(str(path))
        fps = cap.get(cv2.CAP_PROP_FPS)
        cap.release()
        if fps and fps > 0:
            return float(fps)
    raise ValueError(
        "fuse: no frame rate given and none readable from the source videos "
        f"{sorted(map(str, videos.values()))}; pass fps (pipeline.yaml: scenes.NAME.fps)"
    )


def _save_npy(path: Path, array: np.ndarray) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, array)

    atomic_write(path, write)


def _fits_to_arrays(fits: list[PersonFit]) -> dict[str, np.ndarray]:
    out = {}
    for k, f in enumerate(fits):
        for name, value in dataclasses.asdict(f).items():
            out[f"{k}.{name}"] = np.asarray(value)
    out["n"] = np.array(len(fits))
    return out


def _fits_from_npz(path: Path) -> list[PersonFit]:
    with np.load(path, allow_pickle=False) as z:
        n = int(z["n"])
        fields = [f.name for f in dataclasses.fields(PersonFit)]
        fits = []
        for k in range(n):
            d = {name: z[f"{k}.{name}"] for name in fields}
            d["person_id"] = int(d["person_id"])
            d["single_view"] = bool(d["single_view"])
            d["sigma_px"] = float(d["sigma_px"])
            fits.append(PersonFit(**d))
    return fits


def _fit_batches(
    body, markers, people, tris, fps, o, work: Path, rnd: int | str, progress, log, silhouettes,
    floor, up,
):  # fmt: skip
    """All people fitted in fixed batches, each saved in `work` as it is done (resumable)."""
    fits: list[PersonFit] = []
    batches = range(0, len(people), o.people_per_batch)
    if progress is not None:
        batches = progress(batches, description="body fit (batches of people)", total=len(batches))
    for a in batches:
        path = work / f"fit_{rnd}_{a:06d}.npz"
        if path.is_file():
            fits += _fits_from_npz(path)
            continue
        # torch's thread count is process-wide: `torch_threads` puts it back after the fit
        with torch_threads(o.threads):
            part = fit_people(
                body, markers, people[a : a + o.people_per_batch],
                tris[a : a + o.people_per_batch], fps, o.fit, silhouettes=silhouettes,
                floor=floor, up=up,
            )  # fmt: skip
        atomic_save_npz(path, **_fits_to_arrays(part))
        fits += part
        if log is not None:
            log.info("fuse: fitted people %d-%d of %d", a + 1, a + len(part), len(people))
    return fits


def _exchange_against_fits(
    people: list[PersonObservations], fits: list[PersonFit], o: FuseOptions
) -> tuple[list[PersonObservations], int]:
    """Each person's views with the limb groups the fitted body says were read mirrored
    exchanged; and how many (view, group) pairs that was."""
    consensus = o.regroup.consensus if o.regroup is not None else ConsensusOptions()
    out, total = [], 0
    for p, f in zip(people, fits, strict=True):
        # the fit's frames hold every observed frame (gst.fuse.start.dense_frames)
        markers = f.markers[np.searchsorted(f.frames, p.frames)]
        swap = exchanges_against_body(p, markers, consensus)
        total += int(swap.sum())
        out.append(exchange_groups(p, swap) if swap.any() else p)
    return out, total


def _judge_readings(
    people: list[PersonObservations],
    fits: list[PersonFit],
    stored: np.ndarray,
    read_again: np.ndarray,
    o: FuseOptions,
) -> tuple[list[PersonObservations], int]:
    """Each person's views read again (gst.fuse.relook) given back their first reading,
    `stored`, where the fitted body says that one was the better; and how many views that was."""
    consensus = o.regroup.consensus if o.regroup is not None else ConsensusOptions()
    again = np.zeros(len(stored), bool)
    again[read_again] = True
    out, total = [], 0
    for p, f in zip(people, fits, strict=True):
        rows = p.rows
        candidates = (rows >= 0) & again[np.clip(rows, 0, None)]
        other = np.full(p.uv.shape[:3] + (3,), np.nan)
        other[candidates] = stored[rows[candidates]]
        markers = f.markers[np.searchsorted(f.frames, p.frames)]
        back = candidates & readings_against_body(p, other, markers, consensus, o.relook.gain)
        total += int(back.sum())
        if back.any():
            uv, conf = p.uv.copy(), p.confidence.copy()
            uv[back] = other[back][..., :2]
            conf[back] = np.clip(np.nan_to_num(other[back][..., 2]), 0, 1)
            p = dataclasses.replace(p, uv=uv, confidence=conf)
        out.append(p)
    return out, total


def _readable_only(people: list[PersonObservations], log) -> list[PersonObservations]:
    """The people the fit has something to work with (PersonObservations.readable); the others,
    e.g. a person whose every view was projected from the extraction's skeleton, not read, are
    left out and the log names them."""
    kept = [p for p in people if p.readable]
    if len(kept) < len(people) and log is not None:
        ids = sorted({p.person_id for p in people} - {p.person_id for p in kept})
        log.warning(
            "fuse: people %s left out: no view shows %d landmarks above confidence %.1f",
            ids, READABLE_LANDMARKS, READABLE_CONFIDENCE,
        )  # fmt: skip
    return kept


def _log_rotation(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(R)[0].ravel()


def _on_frames(values: np.ndarray, frames: np.ndarray, dense: np.ndarray) -> np.ndarray:
    out = np.full(len(dense), np.nan)
    out[np.searchsorted(dense, frames)] = values
    return out


MAX_CAMERAS = 63  # one bit each in the int64 views masks


def check_store_calibration(store: CropStore, rig, tolerance: float = 1e-4) -> None:
    """The crops' own cameras are what the bodies are fitted in (every crop carries its R, t);
    the rig names the cameras and draws the overlays. A rig other than the one the crops were
    cut with (recalibrated since the extraction) gave bodies in the old calibration and
    overlays in the new one, without a word: refused, naming the camera. `tolerance`: the
    largest difference of a rotation entry, or of a translation in metres (a rig saved again in
    another format keeps well within it)."""
    R, t = store.read_column("R"), store.read_column("t")
    cam = store.index.column("camera_index").to_numpy()
    for ci, name in enumerate(store.camera_names):
        rows = np.flatnonzero(cam == ci)
        if not len(rows):
            continue
        dR = float(np.abs(R[rows] - rig[name].R).max())
        dt = float(np.abs(t[rows] - rig[name].t).max())
        if dR > tolerance or dt > tolerance:
            raise ValueError(
                f"{store.path}: camera {name}'s crops were cut with another calibration than "
                f"the rig given (rotation entries up to {dR:.2g} apart, translation up to "
                f"{dt:.2g} m): extract again with this rig, or fuse with the rig of the "
                "extraction"
            )


def fuse_scene(
    store_path: str | Path,
    rig,
    out_dir: str | Path,
    report_dir: str | Path,
    *,
    fps: float | None = None,
    options: FuseOptions | None = None,
    landmarks: np.ndarray | Callable | None = None,
    truth_dir: str | Path | None = None,
    videos: dict[str, Path] | None = None,
    progress=None,
    log=None,
    reading_cache: str | Path | None = None,
) -> FuseResult:
    """Fuse every person of the crop store at `store_path` (cameras of `rig`, a calibration Rig).

    `landmarks`: per-crop landmarks (array or function, see group_by_person); default: the
    store's own, else BlazePose on the crops. `truth_dir`: a synthetic scene folder (`synth/`)
    to score against. `videos`: camera -> source video for the overlays (default: the store's
    `source_videos`). `fps`: the capture's frame rate (default: the first source video's).
    `reading_cache`: a folder where the landmark model's readings of crowded crops are kept
    between runs and stages (gst.detect.reading_cache; None: none kept).
    """
    o = options or FuseOptions()
    out_dir, report_dir = Path(out_dir), Path(report_dir)
    work = out_dir / ".work"
    store = CropStore(store_path)
    cams = store.camera_names
    missing = [c for c in cams if c not in rig.names]
    if missing:
        raise ValueError(f"{store_path}: cameras {missing} are not in the rig ({rig.names})")
    if len(cams) > MAX_CAMERAS:
        # the views masks (landmarks.parquet, bodies.parquet) are int64 bit masks: a 64th
        # camera's bit was the sign, a 65th's none
        raise ValueError(
            f"{store_path}: {len(cams)} cameras; fusion takes at most {MAX_CAMERAS} (the views "
            "masks of its Parquet files hold one bit per camera in an int64): extract a subset"
        )
    check_store_calibration(store, rig)
    if videos is None:
        sources = json.loads(store.attrs.get("source_videos", "{}"))
        videos = {k: Path(v) for k, v in sources.items() if Path(v).is_file()}
    if fps is None:
        fps = _video_fps(videos)
    stride = int(store.attrs.get("setting.frame_stride", 1)) or 1
    if stride != 1:
        # the fit's smoothness, the temporal votes, the spike test and the gap filling take
        # frames 1 apart for neighbours: skipped frames read as gaps (half the rows 'gap-filled'
        # at stride 2) or switched those terms off (stride 5 and more)
        raise ValueError(
            f"{store_path}: extracted every {stride}th frame (extract.frame_stride {stride}); "
            "fusing needs every frame: extract with frame_stride 1"
        )
    # the store's file stat too: an extraction run again (same row count or not) must not meet
    # the landmarks cached from the previous one; given landmarks and the rig likewise
    stat = store.path.stat()
    settings = {
        "options": o.settings(),
        "store": [len(store), stat.st_size, stat.st_mtime_ns],
        "fps": fps,
        "landmarks": _landmarks_key(landmarks),
        "rig": _digest(rig_json.to_dict(rig)),
    }
    key = _digest(settings)
    stamp = work / "settings.json"
    if stamp.is_file() and json.loads(stamp.read_text()).get("key") != key:
        shutil.rmtree(work)  # another configuration: start over
    work.mkdir(parents=True, exist_ok=True)  # after the checks: a refused input leaves none
    atomic_write(stamp, lambda t: Path(t).write_text(json.dumps({"key": key})))

    lm_path = work / "landmarks.npy"
    if landmarks is None:
        if lm_path.is_file():
            landmarks = np.load(lm_path)
        else:
            landmarks = crop_landmarks(
                store, progress=progress, refine=o.refine_landmarks, masked=o.mask_others
            )
            _save_npy(lm_path, landmarks)
    stored, read_again = landmarks, np.zeros(0, np.int64)
    if o.relook is not None and not callable(landmarks):
        relook_path = work / "landmarks_relook.npz"
        if relook_path.is_file():
            with np.load(relook_path) as z:
                landmarks, read_again = z["landmarks"], z["rows"]
        else:
            cache = None
            if reading_cache is not None:
                from gst.detect.reading_cache import ReadingCache

                cache = ReadingCache(reading_cache, o.relook.refine)
            relooked = relook_crowded(store, landmarks, o.relook, progress=progress, cache=cache)
            landmarks, read_again = relooked.landmarks, relooked.rows
            atomic_save_npz(relook_path, landmarks=landmarks, rows=read_again)
            if cache is not None:
                cache.save()
                if log is not None and cache.hits:
                    log.info("fuse: %d crowded crops' readings kept from earlier runs (%s)",
                             cache.hits, cache.path)  # fmt: skip
        if log is not None:
            log.info(
                "fuse: %d of %d crops crowded by other people, read again with them painted over",
                len(read_again), len(store),
            )  # fmt: skip
        if o.relook.first == "stored":  # fit the extraction's readings, then judge the others
            landmarks, stored = stored, landmarks
    people = group_by_person(store, landmarks)
    if o.regroup is not None:
        people, regrouped = regroup_people(people, o.regroup, fps)
        if log is not None:
            log.info(
                "fuse: %d people after regrouping (%d crops moved to another person)",
                regrouped.tracks, regrouped.moved_crops,
            )  # fmt: skip
    people = _readable_only(people, log)
    silhouettes = None
    if o.silhouettes and (o.triangulation.consensus_views or o.fit.w_silhouette > 0):
        sizes = {c.name: (c.width, c.height) for c in rig.cameras}
        silhouettes = crop_silhouettes(store, sizes, progress=progress)

    def triangulate(people: list[PersonObservations]) -> list:
        return [triangulate_person(p, o.triangulation, silhouettes) for p in people]

    tris = triangulate(people)
    body = load_body_model(o.body_model)
    markers = MarkerModel.load(o.markers)
    if (other_body := markers.fitted_for(o.body_model)) is not None:
        if log is not None:
            log.warning("fuse: %s", other_body)
        else:
            warnings.warn(other_body, stacklevel=2)
    up = np.asarray(rig.up, np.float64)
    floor = scene_floor(
        [t.points if t is not None else None for t in tris], up, o.floor,
        [p.person_id for p in people], log,
    )  # fmt: skip

    def fit_all(people: list[PersonObservations], tris: list, rnd: int | str) -> list[PersonFit]:
        return _fit_batches(
            body, markers, people, tris, fps, o, work, rnd, progress, log, silhouettes, floor, up
        )

    corrections = np.zeros((len(cams), 3))
    for rnd in range(o.refine_rig_rounds + 1):
        fits = fit_all(people, tris, rnd)
        if rnd == o.refine_rig_rounds:
            break
        path = work / f"rig_{rnd}.npy"
        if path.is_file():
            w = np.load(path)
        else:
            w = camera_corrections(fits, people, len(cams))
            _save_npy(path, w)
        apply_corrections(people, w)
        corrections = np.stack(
            [
                _log_rotation(rotation_matrix(a) @ rotation_matrix(b))
                for a, b in zip(w, corrections, strict=True)
            ]
        )
        tris = triangulate(people)
        if log is not None:
            log.info(
                "fuse: camera corrections (deg) %s",
                np.round(np.degrees(np.linalg.norm(w, axis=1)), 2).tolist(),
            )
    if len(read_again) and o.relook.judge:
        people, n = _judge_readings(people, fits, stored, read_again, o)
        if n:
            tris = triangulate(people)
            fits = fit_all(people, tris, "readings")
        if log is not None:
            log.info("fuse: %d views read again kept their first reading (the body's choice)", n)
    exchanged = 0
    for k in range(o.exchange_rounds):
        people, n = _exchange_against_fits(people, fits, o)
        if not n:
            break
        exchanged += n
        tris = triangulate(people)
        fits = fit_all(people, tris, o.refine_rig_rounds + 1 + k)
        if log is not None:
            log.info("fuse: %d view limb groups read mirrored, exchanged and refitted", n)
    for k in range(o.spike_rounds if o.spike_m is not None else 0):
        people, n = drop_spikes(people, fits, o.spike_m, fps)
        if log is not None:
            log.info("fuse: %d landmark-frames jumped away from their neighbours", n)
        if not n:
            break
        people = _readable_only(people, log)  # a person seen in one frame may have lost it
        tris = triangulate(people)
        fits = fit_all(people, tris, f"spikes_{k}")
    dense_tris = [
        dense_triangulation(t, p.frames, f.frames)
        for t, p, f in zip(tris, people, fits, strict=True)
    ]
    evidence = [joint_evidence(f, t) for f, t in zip(fits, dense_tris, strict=True)]
    n_frames = int(store.attrs.get("n_frames", 0)) or (
        int(max(f.frames.max() for f in fits)) + 1 if fits else 0
    )
    truth = None
    if truth_dir is not None and fits:
        from gst.fuse.evaluate import compare_with_truth, visible_person_frames
        from synth.truth import read_scene_truth, read_truth_views

        expected = visible_person_frames(read_truth_views(truth_dir), range(n_frames), cameras=cams)
        truth = compare_with_truth(fits, read_scene_truth(truth_dir), body, expected=expected)
        truth = truth.as_dict()
    limbs = per_frame_limb_lengths(
        body, markers, people, tris, fps, o.fit,
        marker_offsets=[f.marker_offsets for f in fits],
    )  # fmt: skip
    limbs = [
        {k: _on_frames(v, p.frames, f.frames) for k, v in per.items()}
        for per, p, f in zip(limbs, people, fits, strict=True)
    ]
    summary = summarise(fits, dense_tris, evidence, cams, n_frames, truth, limbs)
    summary.exchanged_view_groups = exchanged
    summary.camera_corrections_deg = (
        {}
        if not o.refine_rig_rounds
        else {
            c: round(float(np.degrees(np.linalg.norm(w))), 3)
            for c, w in zip(cams, corrections, strict=True)
        }
    )

    bodies = out_dir / "bodies.parquet"
    write_bodies(
        bodies, fits, evidence, fps=fps, camera_names=cams,
        model={"name": "gst-fuse", "body_model": o.body_model, "markers": markers.info,
               "version": 1},
        settings=o.settings(), settings_sha256=key,
        stats={"people": len(fits), "rows": int(sum(len(f.frames) for f in fits)),
               "crops": len(store)},
        world_up=up,
    )  # fmt: skip
    lm_out = out_dir / "landmarks.parquet"
    write_landmarks(
        lm_out, [p.person_id for p in people], [p.frames for p in people], tris, cams, fps, up
    )
    trc, c3d = [], []
    for folder, suffix in (("trc", ".trc"), ("c3d", ".c3d")):
        # an earlier fusion into this folder with other people must not leave theirs beside
        # this one's (the stage writes into a fresh folder; a library caller may not)
        for old in (out_dir / folder).glob(f"person_*{suffix}"):
            old.unlink()
    for folder in (out_dir, out_dir / "trc", out_dir / "c3d", report_dir, report_dir / "overlay"):
        # a write killed between its temporary file and the rename leaves a hidden
        # `.<name>.<random>.tmp<suffix>` (gst.atomic): not an output, and not to be moved along
        for leftover in folder.glob(".*.tmp*"):
            if leftover.is_file():
                leftover.unlink()
    for f, ev in zip(fits, evidence, strict=True):
        t_path = out_dir / "trc" / f"person_{f.person_id}.trc"
        c_path = out_dir / "c3d" / f"person_{f.person_id}.c3d"
        write_trc(t_path, f.frames, f.joints, fps, up=up)
        valid = ~ev.fitted_only()
        write_c3d(c_path, f.frames, f.joints, fps, valid=valid, up=up, cameras=ev.camera_mask())
        trc.append(t_path)
        c3d.append(c_path)
    write_report(summary, report_dir, fits, dense_tris, limbs)
    fitted_rig = corrected_rig(rig, cams, corrections)
    overlays: list[Path] = []
    if o.overlay and fits:
        from gst.fuse.overlay import write_overlays

        if videos is None:
            videos = {
                k: Path(v) for k, v in json.loads(store.attrs.get("source_videos", "{}")).items()
            }
        videos = {k: v for k, v in videos.items() if Path(v).is_file()}
        overlays = write_overlays(
            fits,
            body,
            fitted_rig,
            videos,
            report_dir / "overlay",
            progress=progress,
        )
    shutil.rmtree(work)
    return FuseResult(bodies, lm_out, trc, c3d, overlays, summary, fits, fitted_rig)
