"""People in crowds: per-camera BlazePose, keypoint association and refinement, against truth.

    python benchmarks/bench_crowd_people.py SCENE_DIR [SCENE_DIR ...] [--frames N] [--old]

Each SCENE_DIR is a rendered synth scene (e.g. the `crowd` preset: `synth.preset("crowd",
seed=7000)` rendered with `synth.render_scene`), with its board clip (the empty stage, used as
the clean plate, as the extract stage does for synthetic scenes). Variants, on the same frames:

- `old`: `gst.data.extract_scene` with the background model and the visual-hull association
  (`association_method="hull"`; its own report's numbers; missed views by the same 30 %-visible
  criterion as the other rows). It reads whole clips, so `--old` refuses `--frames`.
- `keypoints`: BlazePose per camera (`PersonSegmenter`: detector, tracked regions), keypoint
  association across cameras and 3D ids (`gst.data.keypoints.CrowdTracker`, no refinement);
  masks by capsule ownership of the clean-plate foreground.
- `keypoints + refine`: the same, then every person is looked at again in every camera with
  the other people painted out by the clean plate.

Scores: mask IoU (mean over the views produced), association accuracy
(`gst.data.evaluate.association_accuracy`), missed views (truth views where at least 30% of the
person's joints are visible, `truth/views.parquet`, with no view of that person), id switches
(changes of the id that holds most of a truth person's views, frame to frame), and camera-frames
per second on one core. The rates differ in what they hold: the keypoint rows time BlazePose and
the association only (the videos are decoded and the clean-plate foreground is computed before
the clock starts; `phase_s` is printed beside them), the old row times the whole
`extract_scene` (decoding, background model, masks, crops written, truth scored).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from calibration.formats import read_rig  # noqa: E402
from gst.data.background import BackgroundConfig, build_background  # noqa: E402
from gst.data.evaluate import CropTruth, association_accuracy, match_truth  # noqa: E402
from gst.data.keypoints import PersonInstance  # noqa: E402
from gst.data.keypoints.people import CrowdConfig, CrowdTracker  # noqa: E402
from gst.data.masks import MaskConfig, clean_mask  # noqa: E402
from gst.detect.blazepose import BlazePose  # noqa: E402
from gst.detect.persons import PersonSegmenter, SegmenterConfig, skeleton_support  # noqa: E402
from synth.io import read_masks  # noqa: E402

MIN_VISIBLE = 0.3


def read_video(path: Path, limit: int | None = None) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while limit is None or len(out) < limit:
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    cap.release()
    return out


def phase1(model: BlazePose, frames: list[np.ndarray]) -> tuple[list, float]:
    """Per frame: (instances, their masks) from BlazePose on one camera; seconds."""
    seg = PersonSegmenter(model, SegmenterConfig())
    out = []
    t0 = time.perf_counter()
    for img in frames:
        labels, people = seg.segment(img)
        insts, masks = [], []
        for k, p in enumerate(people):
            m = labels == k + 1
            ys, xs = np.nonzero(m)
            box = (
                (xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5)
                if len(xs)
                else None
            )
            insts.append(PersonInstance.create(p.landmarks, box, p.presence))
            masks.append(m)
        out.append((insts, masks))
    return out, time.perf_counter() - t0


def make_segment(model: BlazePose, width: float = 0.08):
    def segment(camera: str, image: np.ndarray, roi, origin=(0, 0)):
        s = model.segment(image, roi)
        near = skeleton_support(s.landmarks, image.shape[:2], width * roi.side)
        return s.landmarks, s.presence, np.where(near, s.probability, 0.0)

    return segment


def score(rows, vis, truth_frames, n_frames) -> dict:
    acc, n = association_accuracy([CropTruth(*r[:5]) for r in rows])
    got = {(r[0], r[1], r[3]) for r in rows}
    views = [
        k for k, s in vis.items() if k[0] < n_frames and s >= MIN_VISIBLE and k in truth_frames
    ]
    missed = sum(k not in got for k in views)
    by: dict = {}
    for f, _cam, pid, tid, _ in rows:
        if tid:
            by.setdefault(tid, {}).setdefault(f, []).append(pid)
    switches = 0
    for frames in by.values():
        seq = [np.bincount(frames[f]).argmax() for f in sorted(frames)]
        switches += sum(a != b for a, b in zip(seq, seq[1:], strict=False))
    return dict(
        views=n,
        iou=float(np.mean([r[4] for r in rows])) if rows else float("nan"),
        association=acc,
        missed=missed,
        truth_views=len(views),
        ids=len({r[2] for r in rows}),
        switches=switches,
    )


def run_scene(scene: Path, n_frames: int | None, old: bool) -> list[tuple[str, dict]]:
    meta = json.loads((scene / "scene.json").read_text())
    rig = read_rig(scene / "calibration" / "rig.json")
    names = rig.names
    videos = {n: read_video(scene / "videos" / f"{n}.mp4", n_frames) for n in names}
    T = len(videos[names[0]])
    truth = {n: read_masks(scene / "truth" / "masks" / f"{n}.h5")[0] for n in names}
    v = pq.read_table(scene / "truth" / "views.parquet").to_pandas()
    vis = {
        (int(f), str(c), int(p)): float(np.mean(s))
        for f, c, p, s in zip(v.frame, v.camera, v.person_id, v.visible, strict=True)
    }
    present = {
        (f, n, int(p)) for n in names for f in range(T) for p in np.unique(truth[n][f]) if p > 0
    }
    plates = {n: read_video(scene / "board" / f"{n}.mp4") for n in names}
    bgs = {n: build_background(np.stack(plates[n]), BackgroundConfig()) for n in names}
    backs = {n: np.clip(bgs[n].background, 0, 255).astype(np.uint8) for n in names}
    fg = {
        n: [clean_mask(bgs[n].foreground(img), MaskConfig())[0] > 0 for img in videos[n]]
        for n in names
    }
    model = BlazePose(threads=1)
    detections, t_detect = {}, 0.0
    for n in names:
        detections[n], secs = phase1(model, videos[n])
        t_detect += secs
    cf = T * len(names)
    results = []
    for name, refine in (("keypoints", False), ("keypoints + refine", True)):
        tracker = CrowdTracker(
            rig,
            1 / meta["fps"],
            CrowdConfig(refine=refine),
            make_segment(model) if refine else None,
        )
        rows = []
        t0 = time.perf_counter()
        for f in range(T):
            out = tracker.process(
                f,
                {n: detections[n][f][0] for n in names},
                {n: fg[n][f] for n in names},
                {n: videos[n][f] for n in names},
                backs,
                {n: detections[n][f][1] for n in names},
            )
            for person in out.people:
                for n, view in person.views.items():
                    tid, iou = match_truth(view.mask, truth[n][f])
                    rows.append((f, n, person.pid, tid, iou))
        secs = time.perf_counter() - t0
        s = score(rows, vis, present, T)
        s["cam_frames_per_s"] = cf / (t_detect + secs)
        s["phase_s"] = {"detect": t_detect, "associate": secs}
        results.append((name, s))
    if old:
        from gst.data import ExtractOptions, extract_scene

        work = Path(tempfile.mkdtemp(prefix="bench_crowd_"))
        try:
            t0 = time.perf_counter()
            rep = extract_scene(
                {n: scene / "videos" / f"{n}.mp4" for n in names},
                rig,
                work / "crops.h5",
                truth=scene / "truth",
                options=ExtractOptions(
                    background_videos={n: scene / "board" / f"{n}.mp4" for n in names},
                    # "auto" resolves to the keypoint association wherever BlazePose is
                    # installed, and this benchmark needs it installed
                    association_method="hull",
                ),
            )
            secs = time.perf_counter() - t0
            results.insert(
                0,
                (
                    "old (background + hull)",
                    dict(
                        views=rep.crops,
                        iou=float("nan") if rep.mask_iou is None else rep.mask_iou,
                        association=(
                            float("nan")
                            if rep.association_accuracy is None
                            else rep.association_accuracy
                        ),
                        # the keypoint rows' criterion (>= 30 % of the joints visible)
                        missed=rep.visible_views_missed,
                        truth_views=rep.visible_views,
                        ids=rep.persons,
                        switches=-1,
                        cam_frames_per_s=rep.frames_considered * len(names) / secs,
                        phase_s={"whole stage": secs},
                    ),
                ),
            )
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return results


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--old", action="store_true", help="also run the old extraction")
    args = ap.parse_args()
    if args.old and args.frames is not None:
        ap.error("--old runs extract_scene on whole clips: leave out --frames to compare it")
    totals: dict[str, list] = {}
    print(
        f"{'scene':28s} {'variant':26s} {'cam-fr/s':>8s} {'views':>6s} {'IoU':>6s} "
        f"{'assoc':>6s} {'missed':>12s} {'ids':>4s} {'switch':>6s}"
    )
    for scene in args.scenes:
        for name, s in run_scene(scene, args.frames, args.old):
            totals.setdefault(name, []).append(s)
            print(
                f"{scene.name:28s} {name:26s} {s['cam_frames_per_s']:8.2f} {s['views']:6d} "
                f"{s['iou']:6.3f} {s['association']:6.3f} "
                f"{s['missed']:5d}/{s['truth_views']:<5d} "
                f"({s['missed'] / max(s['truth_views'], 1):.3f}) "
                f"{s['ids']:4d} {s['switches']:6d}  "
                + " ".join(f"{k} {v:.1f}s" for k, v in s.get("phase_s", {}).items()),
                flush=True,
            )
    print("\nmeans over scenes (cam-frames/s: median):")
    for name, ss in totals.items():
        print(
            f"  {name:26s} IoU {np.mean([s['iou'] for s in ss]):.3f}  association "
            f"{np.mean([s['association'] for s in ss]):.3f}  missed "
            f"{np.mean([s['missed'] / max(s['truth_views'], 1) for s in ss]):.3f}  "
            f"cam-frames/s {np.median([s['cam_frames_per_s'] for s in ss]):.2f}"
        )


if __name__ == "__main__":
    main()
