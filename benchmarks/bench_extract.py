"""Throughput of person extraction at 1080p: frames per second per camera, next to mask error.

    python benchmarks/bench_extract.py                 # synthetic 1080p scene with truth
    python benchmarks/bench_extract.py --repeats 3 --frames 40
    python benchmarks/bench_extract.py --real ../shared/real/pose2sim-multiperson \\
        --calib ../shared/real/pose2sim-multiperson/Calib.qca.txt --format qualisys
    python benchmarks/bench_extract.py --scenes workspace/crowd_7000/synth ...   # old vs new

`--scenes` compares the associations on rendered synthetic scenes (e.g. the `crowd` preset),
each with its board clip as the clean plate and its truth, in one run: the background model
with the visual hull (the old default), BlazePose masks with the visual hull, and the keypoint
association (BlazePose instances on every camera, matched by landmark geometry, tracked in 3D,
refined with neighbours painted out). Missed views are counted both by the store's area
criterion and among truth views where >= 30% of the person's joints are visible.

The synthetic input is the test scene renderer (tests/extract_scenes.py) at 480x270, upscaled
to 1920x1080 (so the content is soft, but the decoding, background, association, cropping and
storage work is that of 1080p), with truth masks upscaled alike. Each variant runs the whole
`extract_scene` serially (one process); "cam-frames/s" is frames x cameras / seconds, i.e.
the frames per second one camera's stream is processed at on one core. Medians over repeats;
ratios against the first variant (the stage's default without the detect extra: the
background model and the hull) measured in the same run; with the detect extra the stage's
default is the keypoint variant.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import add_scene_size, bench_parser  # noqa: E402
from benchmarks.summary import known_mean, left_out  # noqa: E402
from calibration import Camera, Rig  # noqa: E402
from gst.data import ExtractOptions, extract_scene  # noqa: E402
from gst.detect.persons import SegmenterConfig  # noqa: E402


def synthetic_1080p(root: Path, n_frames: int, n_people: int) -> tuple[dict, Rig, Path]:
    """Render a small scene and upscale it x4 to 1920x1080 (videos, truth masks and intrinsics)."""
    from tests.extract_scenes import make_scene

    small = make_scene(
        root / "small", n_people=n_people, n_frames=n_frames, size=(480, 270), laps=0.6
    )
    up = 4
    cams, videos = [], {}
    (root / "truth" / "masks").mkdir(parents=True, exist_ok=True)
    (root / "videos").mkdir(parents=True, exist_ok=True)
    for cam in small.rig:
        # Pixel centres: u_big = (u + 0.5) * up - 0.5, so cx' = (cx + 0.5) up - 0.5, f' = f up.
        K = cam.K.copy()
        K[:2, :2] *= up
        K[:2, 2] = (K[:2, 2] + 0.5) * up - 0.5
        cams.append(
            Camera.create(cam.name, K, cam.dist, cam.R, cam.t, cam.width * up, cam.height * up)
        )
        cap = cv2.VideoCapture(str(small.videos[cam.name]))
        path = root / "videos" / f"{cam.name}.mp4"
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (cam.width * up, cam.height * up)
        )
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            writer.write(cv2.resize(frame, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC))
        writer.release()
        videos[cam.name] = path
        masks = np.load(small.truth / "masks" / f"{cam.name}.npz")["masks"]
        big = np.stack(
            [cv2.resize(m, None, fx=up, fy=up, interpolation=cv2.INTER_NEAREST) for m in masks]
        )
        np.savez_compressed(root / "truth" / "masks" / f"{cam.name}.npz", masks=big)
    shutil.rmtree(root / "small")
    return videos, Rig(tuple(cams)), root / "truth"


VARIANTS = [
    # name, method, work_scale (None = default: longer side 960 px), compression, person model
    # the stage's default without the detect extra (hull association); with it, "keypoints"
    ("median, work 1/2 (default without the detect extra)", "median", None, "gzip", False),
    ("median, work 1/4", "median", 0.25, "gzip", False),
    ("median, work 1/1", "median", 1.0, "gzip", False),
    ("mog2, work 1/2", "mog2", None, "gzip", False),
    ("knn, work 1/2", "knn", None, "gzip", False),
    ("median, work 1/2, lzf store", "median", None, "lzf", False),
    # Learned person masks (gst.detect; needs the detect extra and `python -m gst.detect fetch`).
    # (every frame, no zoomed look: not the keypoint default's person model)
    ("blazepose masks, work 1/2", "median", None, "gzip", True),
    # Keypoint association (BlazePose instances, landmarks matched across views), the default:
    # the person detector every 10 frames, people followed by their landmark regions between.
    (
        "keypoints, work 1/2 (the stage's default with the detect extra)",
        "median",
        None,
        "gzip",
        "keypoints",
    ),  # fmt: skip
    # ... with the person detector on every frame (the default before 2026-11-25)
    ("keypoints, detector every frame", "median", None, "gzip", "keypoints-1"),
]


SCENE_VARIANTS = [
    # name, association method, person model, person detector every N frames (keypoints)
    ("background + hull (old)", "hull", "none", 1),
    ("blazepose masks + hull", "hull", "blazepose", 1),
    ("keypoints (default)", "keypoints", "none", 10),
    ("keypoints, detector every frame", "keypoints", "none", 1),
]


def _score(value: float | None) -> str:
    """A 6-wide score column; n/a where the report has none (a scene without crops)."""
    return f"{'n/a':>6s}" if value is None else f"{value:6.3f}"


def compare_on_scenes(scenes: list[Path], chosen: list[int]) -> None:
    """Old and new association on the same synthetic scenes (see the module doc)."""
    from calibration.formats import read_rig
    from gst.data.extract.options import ExtractOptions as Options

    print(
        f"{'scene':24s} {'variant':26s} {'cam-fr/s':>8s} {'crops':>6s} {'IoU':>6s} {'assoc':>6s} "
        f"{'missed (area)':>14s} {'missed (>=30% vis)':>19s} {'ids':>4s} {'single':>6s}"
    )
    totals: dict[str, list] = {}
    for scene in scenes:
        rig = read_rig(scene / "calibration" / "rig.json")
        names = [c.name for c in rig]
        videos = {n: scene / "videos" / f"{n}.mp4" for n in names}
        plates = {n: scene / "board" / f"{n}.mp4" for n in names}
        for name, method, person, every in [SCENE_VARIANTS[i] for i in chosen]:
            work = Path(tempfile.mkdtemp(prefix="bench_extract_"))
            try:
                opts = Options.from_settings(plates, None, person, association_method=method)
                if method == "keypoints":
                    # the stage's person model (zoomed second look included) but for the
                    # detector's interval (a bare SegmenterConfig dropped the zoom)
                    opts = replace(opts, person_detect_every=every)
                t = time.perf_counter()
                rep = extract_scene(
                    videos, rig, work / "crops.h5", truth=scene / "truth", options=opts
                )
                secs = time.perf_counter() - t
            finally:
                shutil.rmtree(work, ignore_errors=True)
            cf = rep.frames_considered * len(names)
            vis = rep.visible_views_missed / max(rep.visible_views, 1)
            totals.setdefault(name, []).append((cf / secs, rep, vis))
            print(
                f"{scene.parent.name if scene.name == 'synth' else scene.name:24s} {name:26s} "
                f"{cf / secs:8.2f} {rep.crops:6d} {_score(rep.mask_iou)} "
                f"{_score(rep.association_accuracy)} "
                f"{rep.truth_views_missed:6d}/{rep.truth_views:<7d} "
                f"{rep.visible_views_missed:6d}/{rep.visible_views:<5d} ({vis:.3f}) "
                f"{rep.persons:4d} {rep.single_view_crops:6d}",
                flush=True,
            )
    print(
        "\nmeans over scenes (cam-frames/s: median; IoU and association over the scenes that have "
        "them: a scene without crops has neither, and is left out, not counted as 0):"
    )
    for name, rows in totals.items():
        iou, no_iou = known_mean(r[1].mask_iou for r in rows)
        assoc, no_assoc = known_mean(r[1].association_accuracy for r in rows)
        print(
            f"  {name:26s} {np.median([r[0] for r in rows]):6.2f} cam-frames/s  IoU {iou:.3f}"
            f"{left_out(no_iou, len(rows), 'scenes')}  association {assoc:.3f}"
            f"{left_out(no_assoc, len(rows), 'scenes')}  missed (>=30% vis) "
            f"{np.mean([r[2] for r in rows]):.3f}"
        )


def mask_support(store_path: Path) -> str:
    """Median and 5th percentile of a store's `mask_support` (keypoint association), or n/a."""
    from gst.data.store import CropStore

    store = CropStore(store_path)
    try:
        v = store.index.column("mask_support").to_numpy() if len(store) else np.zeros(0)
    finally:
        store.close()
    v = v[np.isfinite(v)]
    return f"{np.median(v):.3f} / {np.percentile(v, 5):.3f}" if len(v) else "n/a"


def _chosen(variants: str, n: int) -> list[int]:
    """The variant numbers of `--variants`: comma-separated (0-based) or 'all' (the n of them)."""
    return list(range(n)) if variants == "all" else [int(v) for v in variants.split(",")]


def main() -> None:
    ap = bench_parser(__doc__)
    add_scene_size(ap, frames=30, people=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument(
        "--variants", default="all", help="comma-separated variant numbers (0-based) or 'all'"
    )
    ap.add_argument(
        "--real",
        type=Path,
        help="folder of real <camera>.mp4 videos instead of the synthetic scene",
    )
    ap.add_argument("--calib", type=Path, help="calibration file for --real")
    ap.add_argument("--format", default=None, help="calibration format for --real (e.g. qualisys)")
    ap.add_argument(
        "--scenes", type=Path, nargs="+", help="rendered synth scenes: old vs new association"
    )
    args = ap.parse_args()
    if args.scenes:
        compare_on_scenes(
            args.scenes,
            _chosen(args.variants, len(SCENE_VARIANTS)),
        )
        return

    work = Path(tempfile.mkdtemp(prefix="bench_extract_"))
    try:
        t0 = time.perf_counter()
        if args.real:
            from calibration.formats import read_rig

            rig = read_rig(args.calib, args.format)
            videos = {p.stem: p for p in sorted(args.real.glob("*.mp4")) if p.stem in rig.names}
            truth = None
            what = f"real videos in {args.real}"
        else:
            videos, rig, truth = synthetic_1080p(work / "scene", args.frames, args.people)
            what = f"synthetic {args.people}-person scene, {args.frames} frames"
        cam0 = rig[next(iter(videos))]
        print(
            f"input: {what}; {len(videos)} cameras at {cam0.width}x{cam0.height} "
            f"(prepared in {time.perf_counter() - t0:.1f} s)"
        )
        chosen = _chosen(args.variants, len(VARIANTS))
        rows = []
        for vi in chosen:
            name, method, ws, comp, persons = VARIANTS[vi]
            times, reports = [], []
            for _ in range(args.repeats):
                out = work / f"v{vi}" / "crops.h5"
                if out.parent.exists():
                    shutil.rmtree(out.parent)
                if persons is True:
                    segmenter = SegmenterConfig()
                elif persons == "keypoints-1":  # the keypoint default but for the detector
                    segmenter = SegmenterConfig(detect_every=1, zoom=ExtractOptions().person_zoom)
                else:
                    segmenter = None  # hull without person model; keypoints: its default
                t = time.perf_counter()
                rep = extract_scene(
                    videos,
                    rig,
                    out,
                    method=method,
                    truth=truth,
                    options=ExtractOptions(
                        work_scale=ws,
                        compression=comp,
                        persons=segmenter,
                        association_method="hull" if persons in (True, False) else "keypoints",
                    ),
                )
                times.append(time.perf_counter() - t)
                reports.append(rep)
            rep = reports[int(np.argsort(times)[len(times) // 2])]
            rows.append((name, float(np.median(times)), rep, mask_support(out)))
        base = rows[0][1]
        n_cf = None
        print(f"\n(x first: speed relative to the first variant run, {rows[0][0]})")
        print(
            f"{'variant':30s} {'total s':>8s} {'cam-frames/s':>12s} {'x first':>9s} | "
            f"{'masks':>6s} {'assoc':>6s} {'crops':>6s} {'merge':>6s} (cam-frames/s per phase) | "
            f"{'mask IoU':>8s} {'assoc acc':>9s} {'crops':>6s} ids  support median / p5"
        )
        for name, secs, rep, support in rows:
            n_cf = rep.frames_considered * len(rep.cameras)
            ph = {k: (n_cf / v if v > 0 else float("inf")) for k, v in rep.timings.items()}
            iou = f"{rep.mask_iou:.3f}" if rep.mask_iou is not None else "n/a"
            acc = (
                f"{rep.association_accuracy:.3f}" if rep.association_accuracy is not None else "n/a"
            )
            print(
                f"{name:30s} {secs:8.1f} {n_cf / secs:12.2f} {base / secs:9.2f} | "
                f"{ph.get('masks', 0):6.1f} {ph.get('association', 0):6.1f} "
                f"{ph.get('crops', 0):6.1f} "
                f"{ph.get('merge', 0):6.1f}                         | {iou:>8s} {acc:>9s} "
                f"{rep.crops:6d} {rep.persons:3d}  {support}"
            )
        print(f"\n{n_cf} camera-frames per run; repeats: {args.repeats} (median shown)")
        print(
            "support: the crops' mask_support, the share of the person's unhidden body (capsules "
            "around the triangulated skeleton) their mask covers: mask quality without truth"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
