"""End-to-end tracking throughput: a synthetic 1080p video, and the real lab capture.

The whole loop (decode + detect + crop + predict + track + write Parquet) runs first with
supplied boxes and the pixel-free BoxDepthPredictor (everything except the model), then end to
end with the tiny GST preset (pose-only, the default; random weights unless `--checkpoint`,
since speed does not depend on them), with supplied boxes and with the static-camera background
detector. Variants run in one process on the same video; each is timed
`--repeats` times and the median is reported with its ratio to the video's own frame rate.
Error columns: id switches against the true walkers, and the median pelvis reprojection offset
from the box centre. The baseline puts the pelvis on the ray through the centre of the box (of
the box enclosing it in the undistorted image, with lens distortion), so the offset is 0 px for
a pinhole camera, a few px with distortion, and shows the lag that smoothing adds.

Real footage (`--real`, when the lab capture and the BlazePose models are here): one lab camera
(1088x1920 at 60 fps, 2 people and, in cam01, a bystander), end to end with the learned person model
and the stage's tracker settings (decode, person model, GST, tracker, Parquet). The previous person
model (detector and segmentation on every frame, `SegmentEveryFrame` below) runs in the same process
as the landmark-model loop (gst.track.person_detector) and its variants. Beside each speed: CPU time
per video frame (all threads; less sensitive to other load than wall time), "warm f/s" (video
frames per second between the processed frames at a quarter and three quarters of the clip:
the rate a long video runs at, without the once-per-video start that the clip's 100 frames
carry; `warm_rate`), detector runs, and
against the previous model's tracks (the detector on every frame): id switches (a reference person's
rows changing id) and drift (median and 95th percentile distance of the 12 limb landmarks,
full-resolution pixels, people matched per frame by landmark distance). Variants named "image path
for every crop" run the network's image path for every crop (`image_path: always`, the behaviour
before pose from the landmarks); "every crop cut" takes the pose from the landmarks but still cuts
every crop (what not cutting them saves); "not looking again" leaves out the detector's second look
with the people found painted out (`look_again`, docs/track_evaluation.md "Looking again"): on
cam01 the stage default tracks 3 people (the bystander), without looking again 2: their speeds are
per 3 and per 2 people. "still people computed" runs the landmark model for every tracked person
in every frame (`still_change: 0`; the default keeps the landmarks of a person whose region has
not changed, docs/track_evaluation.md "People who stand still"). "without zoom" / "no zoom" looks
again in the usual detector windows only (`look_again_zoom: 0`; docs/track_evaluation.md "Small
people at the back"). "left/right labels as detected" leaves out the smoother that keeps each
person's left and right continuous (`unmirror`; docs/track_evaluation.md "Left and right").
"detector every 10 frames (before 11-29)" runs the detector for new arrivals every 10 processed
frames, as before its interval became 1/3 s of video (`detect_every_s`; 20 frames at 60 fps;
docs/track_evaluation.md "The detector's interval in seconds"). Each variant's person model is
made for the video's frame rate. The last line times a second run over the video that replays
the detections the first one kept (`keep_detections`, gst.track.detection_cache).

    python benchmarks/bench_track.py [--frames 150] [--repeats 3] [--people 3]
    python benchmarks/bench_track.py --real [--camera cam01] [--real-frames 100] [--repeats 3]
    python benchmarks/bench_track.py --real --checkpoint WS/demo/models/gst.pt --demo WS

With `--demo WS` (a workspace after `run all`) every variant also tracks the demo scene's
camera videos with the demo's own network, and prints MPJPE / PA-MPJPE against the truth,
recall and id switches beside its time: the accuracy of each speed-up in the same run.
"""

from __future__ import annotations

import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import add_scene_size, bench_parser  # noqa: E402
from benchmarks.summary import left_out, weighted_mean  # noqa: E402
from benchmarks.timing import median_time  # noqa: E402
from calibration import Camera  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.data.crop import crop_window, cut_crop  # noqa: E402
from gst.model.checkpoint import save_checkpoint  # noqa: E402
from gst.model.inference import GSTPredictor  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.track import (  # noqa: E402
    OneEuroConfig,
    SuppliedBoxes,
    TrackOptions,
    column_array,
    iter_frames,
    read_tracks,
    track_video,
)
from gst.track.static_detector import StaticCameraDetector  # noqa: E402
from gst.track.tracker import TrackerConfig, box_iou  # noqa: E402
from gst.train.recipe import build_network  # noqa: E402
from tests.track_synthetic import (  # noqa: E402
    Walker,
    render,
    track_boxes,
    walker_boxes,
    write_boxes_csv,
    write_video,
)

W, H, FPS = 1920, 1080, 30.0


def walkers(n: int) -> list[Walker]:
    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        h = rng.uniform(350, 650)
        out.append(
            Walker(
                tuple(int(c) for c in rng.integers(30, 230, 3)),
                (rng.uniform(300, 1600), rng.uniform(450, 650)),
                (rng.uniform(-8, 8), rng.uniform(-1, 1)),
                (0.4 * h, h),
                depth_order=k,
            )
        )
    return out


def distorted_camera() -> Camera:
    K = [[1500.0, 0, 959.5], [0, 1500.0, 539.5], [0, 0, 1]]
    return Camera.create("bench", K, [-0.15, 0.04, 0.0, 0.0, 0.0], np.eye(3), [0.0, 0.0, 0.0], W, H)


def errors(path: Path, boxes: np.ndarray) -> tuple[int, float] | str:
    """(id switches, median pelvis offset px), or "no rows" when the variant tracked nobody
    (the BlazePose detector on the synthetic walkers: the median of nothing printed nan and
    0 switches, as if it had tracked them)."""
    t = read_tracks(path)
    if t.num_rows == 0:
        return "no rows"
    frames = t.column("frame").to_numpy()
    bb = column_array(t, "bbox")
    who = np.array(
        [int(np.argmax(box_iou(b, boxes[f])[0])) for f, b in zip(frames, bb, strict=True)]
    )
    pid = t.column("person_id").to_numpy()
    switches = sum(len(set(pid[who == w])) - 1 for w in np.unique(who))
    centre = (bb[:, :2] + bb[:, 2:]) / 2 - 0.5  # box centre in pixel-centre coordinates
    offset = np.linalg.norm(column_array(t, "joints2d")[:, 0] - centre, axis=1)
    return switches, float(np.median(offset))


def tiny_checkpoint(path: Path) -> Path:
    """A random-weight checkpoint of the tiny preset on the open body model."""
    body = load_body_model("anny")
    net, ids, groups = build_network(get_preset("tiny"), body)
    save_checkpoint(path, net, "anny", ids, groups)
    return path


def warm_rate(stamps: dict[int, float]) -> float:
    """Video frames per second between the processed frames at a quarter and at three quarters
    of a run (`track_video`'s `on_frame` times, video frame indices): the rate once everything
    has started (models loaded, the first frame's detector run, the prefetch thread), which a
    long video runs at. The clip's own rate (the "video f/s" column) carries those once-per-video
    costs over its 100 frames; the left/right smoother hands frames on `lag_s` late, so the last
    quarter arrives in one burst at the end and is left out."""
    frames = sorted(stamps)
    if len(frames) < 8:
        return float("nan")
    a, b = frames[len(frames) // 4], frames[3 * len(frames) // 4]
    return (b - a) / max(stamps[b] - stamps[a], 1e-9)


def main() -> None:
    ap = bench_parser(__doc__)
    add_scene_size(ap, frames=150, people=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--codec", default="mp4v", help="fourcc of the test video (mp4v: MPEG-4 part 2 in .mp4)"
    )
    ap.add_argument(
        "--checkpoint", type=Path, help="a GST checkpoint (default: random-weight tiny preset)"
    )
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    ap.add_argument("--real", action="store_true", help="the lab capture instead (see above)")
    ap.add_argument("--camera", default="cam01", help="lab camera for --real")
    ap.add_argument("--real-frames", type=int, default=100, help="frames of the lab video")
    ap.add_argument(
        "--only", default=None, help="--real: run variants whose name has this text (several: a|b)"
    )
    ap.add_argument(
        "--demo",
        type=Path,
        default=None,
        help="--real: also track the demo scene of this workspace (after `run all`) with each "
        "variant and print its MPJPE against the truth",
    )
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.real:
        real_footage(args)
        return
    tmp = Path(tempfile.mkdtemp(prefix="bench_track_"))
    try:
        ws = walkers(args.people)
        boxes = walker_boxes(ws, args.frames)
        video = write_video(tmp / "bench.mp4", render(ws, boxes, W, H), W, H, FPS, args.codec)
        det = SuppliedBoxes.from_file(write_boxes_csv(tmp / "boxes.csv", boxes, "bench"))
        n = args.frames
        print(
            f"video: {W}x{H} {args.codec}, {n} frames at {FPS:.0f} fps, {args.people} people per "
            f"frame, median of {args.repeats} runs"
        )
        print(
            f"{'variant':44s} {'s':>7s} {'frames/s':>9s} {'x realtime':>10s} {'ms/frame':>9s} "
            f"{'id sw.':>6s} {'pelvis px':>9s}"
        )

        def row(name, seconds, err=None):
            fps = n / seconds
            if isinstance(err, str):
                e = f"{'-':>6s} {err:>9s}"
            else:
                e = f"{err[0]:6d} {err[1]:9.3f}" if err else f"{'-':>6s} {'-':>9s}"
            print(
                f"{name:44s} {seconds:7.2f} {fps:9.1f} {fps / FPS:10.2f} {1000 * seconds / n:9.2f} "
                f"{e}",
                flush=True,
            )

        s, _ = median_time(lambda: sum(1 for _ in iter_frames(video)), args.repeats)
        row("decode only", s)
        s, _ = median_time(lambda: sum(1 for _ in iter_frames(video, prefetch=4)), args.repeats)
        row("decode only, prefetch thread", s)

        frames = [f.image for f in iter_frames(video, end_s=min(n, 30) / FPS)]

        def crops_only():
            for i, img in enumerate(frames):
                for b in boxes[i]:
                    cut_crop(img, crop_window(b, 256))

        s, _ = median_time(crops_only, args.repeats)
        print(
            f"{'  crops alone (256 px, per detection)':44s} "
            f"{1000 * s / (len(frames) * args.people):7.2f} ms"
        )

        variants = [
            ("full loop, batch 32, prefetch 4", TrackOptions(), None),
            ("full loop, batch 32, no prefetch", TrackOptions(prefetch=0), None),
            ("full loop, batch 8", TrackOptions(batch_size=8), None),
            (
                "full loop + One-Euro (1 Hz, beta 0.5)",
                TrackOptions(smoothing=OneEuroConfig()),
                None,
            ),
            (
                "full loop + One-Euro (1 Hz, beta 5)",
                TrackOptions(smoothing=OneEuroConfig(beta=5.0)),
                None,
            ),
            ("full loop, calibrated with lens distortion", TrackOptions(), distorted_camera()),
            ("full loop, stride 2 (time per video frame)", TrackOptions(stride=2), None),
        ]
        for name, options, camera in variants:

            def run(options=options, camera=camera):
                out = tmp / "out"
                shutil.rmtree(out, ignore_errors=True)
                return track_boxes(video, out, det, camera=camera, options=options, resume=False)

            s, res = median_time(run, args.repeats)
            row(name, s, errors(res.path, boxes))

        checkpoint = args.checkpoint or tiny_checkpoint(tmp / "tiny.pt")
        gst = GSTPredictor(checkpoint)
        detectors = [
            (f"end to end, {gst.name} pose-only, supplied boxes", lambda: det),
            (
                f"end to end, {gst.name} pose-only, background detector",
                lambda: StaticCameraDetector(video),
            ),
        ]
        try:  # the learned person detector, when its extra and models are installed
            from gst.detect import BlazePoseModelsMissing, model_paths
            from gst.track.person_detector import PersonModelDetector

            model_paths()
            detectors.append(
                (f"end to end, {gst.name} pose-only, blazepose detector", PersonModelDetector)
            )
        except (ImportError, BlazePoseModelsMissing) as exc:
            print(f"(blazepose detector skipped: {str(exc).splitlines()[0][:100]})")
        for name, detector in detectors:

            def run_gst(detector=detector):
                out = tmp / "out"
                shutil.rmtree(out, ignore_errors=True)
                return track_video(
                    video,
                    out,
                    detector(),
                    gst,
                    model={"name": gst.name, "version": "bench"},
                    options=TrackOptions(),
                    resume=False,
                )

            s, res = median_time(run_gst, args.repeats)
            row(name, s, errors(res.path, boxes))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


LAB = Path("/work/shared/real/pose2sim-multiperson")


class SegmentEveryFrame:
    """The previous person model, kept here as the baseline: the detector on every frame, plus the
    previous frame's regions, the landmark model and full-frame instance masks
    (gst.detect.persons.PersonSegmenter) on every frame; boxes from the masks."""

    def __init__(self, max_side: int = 960, min_height_frac: float = 0.08):
        from gst.detect.blazepose import BlazePose
        from gst.detect.persons import PersonSegmenter, SegmenterConfig

        self.segmenter = PersonSegmenter(BlazePose(), SegmenterConfig())
        self.max_side, self.min_height_frac = max_side, min_height_frac
        self.detector_runs = 0

    def detect(self, frame_bgr, frame_index):
        import cv2

        from gst.track.detection import Detection

        h, w = frame_bgr.shape[:2]
        s = min(1.0, self.max_side / max(h, w))
        small = cv2.resize(frame_bgr, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        labels, people = self.segmenter.segment(small)
        self.detector_runs += 1
        out = []
        for k, person in enumerate(people, start=1):
            ys, xs = np.nonzero(labels == k)
            if len(xs) == 0:
                continue
            box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64) / s
            if box[3] - box[1] < self.min_height_frac * h:
                continue
            if any(float(box_iou(box[None], d.box[None])[0, 0]) > 0.6 for d in out):
                continue
            lm = person.landmarks.copy()
            lm[:, :2] = (lm[:, :2] + 0.5) / s - 0.5
            lm[:, 2] *= person.presence
            out.append(Detection(box=box, score=float(person.presence), landmarks=lm))
        return out


def _limb_landmarks(table) -> np.ndarray:
    from gst.detect.persons import LIMB_JOINTS

    return column_array(table, "landmarks2d")[:, LIMB_JOINTS]


def compare_to_reference(
    path: Path, reference: Path, stride: int = 1
) -> tuple[int, float, float, int]:
    """(id switches, median drift px, p95 drift px, reference rows unmatched) of a tracks file
    against the reference run's, on the frames both processed, people matched per frame by
    median limb-landmark distance."""
    from scipy.optimize import linear_sum_assignment

    t, r = read_tracks(path), read_tracks(reference)
    r = r.filter(pa.array(r.column("frame").to_numpy() % stride == 0))
    ft, fr = t.column("frame").to_numpy(), r.column("frame").to_numpy()
    it, ir = t.column("person_id").to_numpy(), r.column("person_id").to_numpy()
    lt, lr = _limb_landmarks(t), _limb_landmarks(r)
    seq: dict[int, list[int]] = {}
    drift, missed = [], 0
    for f in np.unique(fr):
        a, b = np.flatnonzero(fr == f), np.flatnonzero(ft == f)
        if not len(b):
            missed += len(a)
            continue
        d = np.array([[np.median(np.linalg.norm(lr[i] - lt[j], axis=1)) for j in b] for i in a])
        rows, cols = linear_sum_assignment(d)
        missed += len(a) - len(rows)
        for i, j in zip(rows, cols, strict=True):
            if d[i, j] > 100:  # not the same person
                missed += 1
                continue
            drift.append(d[i, j])
            seq.setdefault(int(ir[a[i]]), []).append(int(it[b[j]]))
    switches = sum(sum(1 for x, y in zip(s, s[1:], strict=False) if x != y) for s in seq.values())
    if not drift:
        return switches, float("nan"), float("nan"), missed
    return switches, float(np.median(drift)), float(np.percentile(drift, 95)), missed


def _cpu(fn) -> float:
    c0 = time.process_time()
    fn()
    return time.process_time() - c0


class CutEveryCrop:
    """A predictor as given, except that the loop cuts every crop (it lacks `needs_pixels`):
    isolates what not cutting the crops of pose-from-landmarks detections saves."""

    def __init__(self, predictor):
        self._predictor = predictor

    def __call__(self, *args, **kwargs):
        return self._predictor(*args, **kwargs)

    def __getattr__(self, name: str):
        if name == "needs_pixels":
            raise AttributeError(name)
        return getattr(self._predictor, name)


def components(video: Path, camera, n: int, gst, fps: float) -> None:
    """CPU ms per frame of the parts of the new loop, each run alone, one after another (each
    on the threads it uses by default: FFmpeg's, LiteRT's, torch's; CPU time over all of them)."""
    from gst.data.camera_view import TrackingView
    from gst.track.frames import prepare_detection
    from gst.track.person_detector import PersonModelDetector

    frames = []
    decode = _cpu(lambda: frames.extend(f.image for f in iter_frames(video, end_s=n / fps)))
    det = PersonModelDetector()
    found = []
    detect = _cpu(lambda: found.extend(det.detect(img, i) for i, img in enumerate(frames)))
    view = TrackingView.for_video(camera.width, camera.height, camera)
    cut = []
    crops = _cpu(
        lambda: cut.extend(
            prepare_detection(view, img, d, 256)
            for img, ds in zip(frames, found, strict=True)
            for d in ds
        )
    )
    images = np.stack([c.crop_rgb for c in cut])
    Ks = np.stack([c.K_crop for c in cut])
    net = _cpu(lambda: [gst(images[i : i + 32], Ks[i : i + 32]) for i in range(0, len(cut), 32)])
    people = len(cut) / len(frames)
    print(
        f"parts alone, CPU ms per frame ({people:.1f} people per frame): decode "
        f"{1000 * decode / n:.1f}, person model {1000 * detect / n:.1f} ({det.detector_runs} "
        f"detector runs, {det.regions} landmark regions, {det.still_kept} kept still), crops + "
        "appearance "
        f"{1000 * crops / n:.1f}, {gst.name} {1000 * net / n:.1f}"
    )


def real_footage(args) -> None:
    from calibration.formats import read_rig
    from gst.detect.weights import model_paths
    from gst.track.person_detector import PersonModelDetector
    from gst.track.scene import TrackSettings, network_threads, person_model_config
    from gst.video import probe_video

    video = LAB / f"{args.camera}.mp4"
    if not video.is_file():
        print(f"(no lab capture at {LAB}; nothing to do)")
        return
    model_paths()  # the learned person model must be installed
    lab_rig = read_rig(LAB / "Calib.qca.txt", "qualisys")
    # the stage passes the rig's up with a calibrated camera (the network's gravity input)
    camera, rig_up = lab_rig[args.camera], tuple(lab_rig.up)
    tmp = Path(tempfile.mkdtemp(prefix="bench_track_real_"))
    try:
        checkpoint = args.checkpoint or tiny_checkpoint(tmp / "tiny.pt")
        # image_path "always": the network's image path for every crop (before "auto" skipped
        # it for pose-only crops with landmarks when the network's image gate is negligible)
        predictors = {
            mode: GSTPredictor(checkpoint, image_path=mode) for mode in ("auto", "always")
        }
        predictors["cut"] = CutEveryCrop(predictors["auto"])
        gst = predictors["auto"]
        info = probe_video(video)
        fps = info.fps
        # the frames there are: with --real-frames beyond the video's length the rates were
        # computed from the asked-for count (200 of the lab's 100 frames: twice the speed)
        n = min(args.real_frames, info.frame_count or args.real_frames)
        tracker = TrackerConfig(min_hits=3, max_misses=30)  # the track stage's defaults

        def opts(**kw):
            return TrackOptions(tracker=tracker, end_s=n / fps, **kw)

        # Factories of a video's person model from its frame rate: what `run track` uses for
        # one video (the detector's interval in frames follows the rate and the stride,
        # `track.detect_every_s`), with the variant's changes.
        def new(**kw):
            return lambda rate: PersonModelDetector(
                replace(person_model_config(TrackSettings(), fps=rate), **kw)
            )

        def new_stride2(**kw):
            return lambda rate: PersonModelDetector(
                replace(person_model_config(TrackSettings(stride=2), fps=rate), **kw)
            )

        def every_frame(rate):
            return SegmentEveryFrame()

        default = person_model_config(TrackSettings(), fps=fps)
        before = 10  # processed frames between detector runs before 11-29 evening, any rate
        torch_default = torch.get_num_threads()
        stage_torch = network_threads(TrackSettings(), "blazepose", 1, 1) or torch_default
        variants = [  # (name, detector factory, options, torch threads, network image path)
            # the old rows keep torch's default threads, as the old stage ran; the new rows the
            # stage's (the "new, N torch threads" row shows what the threads alone change)
            (
                f"old: detector + masks every frame ({torch_default} torch threads)",
                every_frame,
                opts(),
                torch_default,
                "auto",
            ),
            (
                f"new: stage default ({default.threads} LiteRT, {stage_torch} torch threads)",
                new(),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                f"new, detector every {before} frames (before 11-29)",
                new(detect_every=before),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                "new, not looking again (before 11-29)",
                new(look_again=False),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                "new, looking again without zoom (before)",
                new(look_again_zoom=0),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                "new, lost people not looked for again (before)",
                new(lost_retry=0),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                "new, still people computed too (before)",
                new(still_change=0),
                opts(),
                stage_torch,
                "auto",
            ),
            (
                "new, tracker without the skeleton term (before)",
                new(),
                replace(opts(), tracker=replace(tracker, w_skeleton=0.0)),
                stage_torch,
                "auto",
            ),
            (
                "new, left/right labels as detected (before)",
                new(),
                replace(opts(), unmirror=None),
                stage_torch,
                "auto",
            ),
            ("new, image path for every crop", new(), opts(), stage_torch, "always"),
            ("new, pose from landmarks, every crop cut", new(), opts(), stage_torch, "cut"),
            (f"new, {torch_default} torch threads", new(), opts(), torch_default, "auto"),
            ("new, 1 LiteRT thread", new(threads=1), opts(), stage_torch, "auto"),
            ("new, one landmark call per person", new(batch=False), opts(), stage_torch, "auto"),
            # one change against the stage default: prefetch off (torch keeps the stage's threads)
            ("new, no prefetch (one Python thread)", new(), opts(prefetch=0), stage_torch, "auto"),
            (
                f"old, stride 2 ({torch_default} torch threads)",
                every_frame,
                opts(stride=2),
                torch_default,
                "auto",
            ),  # fmt: skip
            ("new, stride 2 (stage default)", new_stride2(), opts(stride=2), stage_torch, "auto"),
            (
                "new, stride 2, not looking again",
                new_stride2(look_again=False),
                opts(stride=2),
                stage_torch,
                "auto",
            ),
            (
                "new, stride 2, no zoom",
                new_stride2(look_again_zoom=0),
                opts(stride=2),
                stage_torch,
                "auto",
            ),
            (
                "new, stride 2, still people computed",
                new_stride2(still_change=0),
                opts(stride=2),
                stage_torch,
                "auto",
            ),
            (
                "new, stride 2, image path every crop",
                new_stride2(),
                opts(stride=2),
                stage_torch,
                "always",
            ),
        ]
        if args.only:
            keep = [v for v in variants if any(o in v[0] for o in args.only.split("|"))]
            variants = [variants[0], *[v for v in keep if v is not variants[0]]]
        print(
            f"lab {args.camera}: {camera.width}x{camera.height} at {fps:.0f} fps, {n} frames, "
            f"{gst.name} pose-only (pose from landmarks where the image gate allows: "
            f"{gst.pose_from_landmarks}), calibrated camera, median of {args.repeats} runs; "
            "reference for ids and drift: the first row"
        )
        print(
            f"{'variant':40s} {'s':>6s} {'proc f/s':>8s} {'video f/s':>9s} {'x real':>6s} "
            f"{'warm f/s':>8s} {'x real':>6s} "
            f"{'CPU ms/f':>8s} {'det runs':>8s} {'id sw.':>6s} {'drift px':>13s} {'missed':>6s}"
        )
        components(video, camera, n, gst, fps)
        reference = None
        for k, (name, make, options, torch_threads, image_path) in enumerate(variants):
            walls, cpus, warms, res, det = [], [], [], None, None
            torch.set_num_threads(torch_threads)
            for _rep in range(args.repeats):
                out = tmp / f"out{k}"
                shutil.rmtree(out, ignore_errors=True)
                det = make(fps)
                stamps: dict[int, float] = {}
                t0, c0 = time.perf_counter(), time.process_time()
                res = track_video(
                    video,
                    out,
                    det,
                    predictors[image_path],
                    model={"name": gst.name, "version": "bench"},
                    camera=camera,
                    options=options,
                    world_up=rig_up,
                    resume=False,
                    on_frame=lambda f, st=stamps: st.setdefault(f, time.perf_counter()),
                )
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
                warms.append(warm_rate(stamps))
            wall, cpu = statistics.median(walls), statistics.median(cpus)
            warm = statistics.median(warms)
            keep_path = tmp / f"tracks{k}.parquet"
            shutil.copyfile(res.path, keep_path)
            if reference is None:
                reference = keep_path
            sw, med, p95, missed = compare_to_reference(keep_path, reference, options.stride)
            print(
                f"{name:40s} {wall:6.2f} {res.frames / wall:8.1f} {n / wall:9.1f} "
                f"{n / wall / fps:6.2f} {warm:8.1f} {warm / fps:6.2f} "
                f"{1000 * cpu / n:8.1f} {det.detector_runs:8d} {sw:6d} "
                f"{med:6.1f}/{p95:6.1f} {missed:6d}",
                flush=True,
            )
        replayed_speed(video, camera, rig_up, gst, opts(), stage_torch, fps, args.repeats, tmp)
        if args.demo is not None:
            demo_accuracy(args.demo, variants, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def replayed_speed(video, camera, rig_up, gst, options, torch_threads, fps, repeats, tmp) -> None:
    """`track` over a video whose person detections an earlier run kept (track.keep_detections,
    gst.track.detection_cache): a first run that keeps them, then `repeats` runs that replay
    them; their rows against the first run's."""
    import pyarrow.parquet as pq

    from gst.track.person_detector import PersonModelDetector
    from gst.track.scene import TrackSettings, _detector_info, person_model_config

    s = TrackSettings()
    info = _detector_info("blazepose", "bench", person_model_config(s, fps=fps))
    torch.set_num_threads(torch_threads)
    cache, walls, cpus, same = tmp / "kept_detections", [], [], True
    first = None
    for rep in range(max(1, repeats) + 1):
        out = tmp / f"replay{rep}"
        shutil.rmtree(out, ignore_errors=True)
        det = PersonModelDetector(person_model_config(s, fps=fps))
        t0, c0 = time.perf_counter(), time.process_time()
        res = track_video(
            video,
            out,
            det,
            gst,
            model={"name": gst.name, "version": "bench"},
            camera=camera,
            options=options,
            world_up=rig_up,
            resume=False,
            detector_info=info,
            detections_cache=cache,
        )
        rows = pq.read_table(res.path).drop_columns(["time_s"]).to_pydict()
        if rep == 0:
            first = rows
            continue
        if res.detections != "replayed":
            raise SystemExit(f"the run after the first did not replay ({res.detections})")
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        same &= rows == first
    wall, n = statistics.median(walls), res.frames
    print(
        f"detections replayed (a second run over the video, track.keep_detections): "
        f"{n / wall:.1f} frames/s ({n / wall / fps:.2f}x real time), CPU "
        f"{1000 * statistics.median(cpus) / n:.1f} ms/frame, median of {len(walls)}; rows the "
        f"same as the first run's: {same}",
        flush=True,
    )


def demo_accuracy(workspace: Path, variants: list, tmp: Path) -> None:
    """The demo's own network on the demo's camera videos (calibrated, the rig's up known, as
    `run track` does), with each variant's person model: MPJPE / PA-MPJPE against the truth
    (matched rows, gst.track.evaluate), recall and id switches over all cameras, beside the
    time. Accuracy of the person model's speed-ups in the same run as their speed."""
    from calibration.formats import read_rig
    from gst.track.evaluate import evaluate_tracks
    from gst.video import probe_video

    scene = workspace / "demo"
    needed = [scene / "calibration" / "rig.json", scene / "models" / "gst.pt", scene / "synth"]
    missing = [str(p) for p in needed if not p.exists()]
    if missing:
        raise SystemExit(f"--demo {workspace}: missing {missing} (run `run all` there first)")
    rig = read_rig(scene / "calibration" / "rig.json")
    predictors = {
        mode: GSTPredictor(scene / "models" / "gst.pt", image_path=mode)
        for mode in ("auto", "always")
    }
    predictors["cut"] = CutEveryCrop(predictors["auto"])
    gst = predictors["auto"]
    videos = sorted(p for p in (scene / "synth" / "videos").glob("*.mp4") if p.stem in rig.names)
    print(
        f"\ndemo: {len(videos)} calibrated cameras, {gst.name} ({scene / 'models' / 'gst.pt'}); "
        "MPJPE / PA-MPJPE mm over matched rows that have one (pelvis-aligned), all cameras; "
        "s: track_video alone (detector built and tracks scored outside the clock)"
    )
    print(f"{'variant':40s} {'s':>6s} {'MPJPE':>6s} {'PA':>6s} {'recall':>6s} {'id sw.':>6s}")
    # one untimed video first: the first variant paid the network's and LiteRT's first calls
    _, make0, options0, threads0, path0 = variants[0]
    torch.set_num_threads(threads0)
    track_video(
        videos[0], tmp / "demo_warmup", make0(probe_video(videos[0]).fps), predictors[path0],
        model={"name": gst.name, "version": "bench"}, camera=rig[videos[0].stem],
        options=replace(options0, end_s=None), world_up=tuple(rig.up), resume=False,
    )  # fmt: skip
    for k, (name, make, options, torch_threads, image_path) in enumerate(variants):
        torch.set_num_threads(torch_threads)
        evals, secs = [], 0.0
        for v in videos:
            det = make(probe_video(v).fps)  # built outside the clock, as in the lab rows
            t0 = time.perf_counter()
            res = track_video(
                v,
                tmp / f"demo{k}",
                det,
                predictors[image_path],
                model={"name": gst.name, "version": "bench"},
                camera=rig[v.stem],
                options=replace(options, end_s=None),
                world_up=tuple(rig.up),
                resume=False,
            )
            secs += time.perf_counter() - t0  # tracking only: the scoring below is not timed
            evals.append(evaluate_tracks(res.path, scene / "synth", v.stem))
        n = sum(e.matches for e in evals)

        # weighted by matches over the videos that have this error: a video whose matches carry
        # no pose error (None) adds neither to the sum nor to the denominator
        def mean(attr: str, evals=evals) -> float:
            return weighted_mean((getattr(e, attr), e.matches) for e in evals)

        unscored = sum(1 for e in evals if e.matches and e.mpjpe_mm is None)
        recall = n / max(sum(e.truth_instances for e in evals), 1)
        print(
            f"{name:40s} {secs:6.1f} {mean('mpjpe_mm'):6.1f} {mean('pa_mpjpe_mm'):6.1f} "
            f"{recall:6.3f} {sum(e.id_switches for e in evals):6d}"
            + left_out(unscored, len(evals), "videos with matches but no pose error"),
            flush=True,
        )


if __name__ == "__main__":
    main()
