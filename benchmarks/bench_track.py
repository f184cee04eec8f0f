"""End-to-end tracking throughput on a synthetic 1080p video, with and without the GST network.

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

    python benchmarks/bench_track.py [--frames 150] [--repeats 3] [--people 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration import Camera  # noqa: E402
from gst.body import load_body_model  # noqa: E402
from gst.data.crop import crop_window, cut_crop  # noqa: E402
from gst.model.checkpoint import save_checkpoint  # noqa: E402
from gst.model.inference import GSTPredictor  # noqa: E402
from gst.model.presets import get_preset  # noqa: E402
from gst.track import (  # noqa: E402
    BoxDepthPredictor,
    OneEuroConfig,
    SuppliedBoxes,
    TrackOptions,
    column_array,
    iter_frames,
    read_tracks,
    track_video,
)
from gst.track.static_detector import StaticCameraDetector  # noqa: E402
from gst.track.tracker import box_iou  # noqa: E402
from gst.train.recipe import build_network  # noqa: E402
from tests.track_synthetic import Walker, render, walker_boxes, write_boxes_csv, write_video  # noqa: E402

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


def errors(path: Path, boxes: np.ndarray) -> tuple[int, float]:
    t = read_tracks(path)
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


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--people", type=int, default=3)
    ap.add_argument(
        "--codec", default="mp4v", help="fourcc of the test video (mp4v: MPEG-4 part 2 in .mp4)"
    )
    ap.add_argument(
        "--checkpoint", type=Path, help="a GST checkpoint (default: random-weight tiny preset)"
    )
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    tmp = Path(tempfile.mkdtemp(prefix="bench_track_"))
    try:
        ws = walkers(args.people)
        boxes = walker_boxes(ws, args.frames)
        video = write_video(tmp / "bench.mp4", render(ws, boxes, W, H), W, H, FPS, args.codec)
        det = SuppliedBoxes.from_file(write_boxes_csv(tmp / "boxes.csv", boxes, "bench"))
        n = args.frames
        print(
            f"video: {W}x{H} {args.codec}, {n} frames at {FPS:.0f} fps, {args.people} people per frame, "
            f"median of {args.repeats} runs"
        )
        print(
            f"{'variant':44s} {'s':>7s} {'frames/s':>9s} {'x realtime':>10s} {'ms/frame':>9s} "
            f"{'id sw.':>6s} {'pelvis px':>9s}"
        )

        def row(name, seconds, err=None):
            fps = n / seconds
            e = f"{err[0]:6d} {err[1]:9.3f}" if err else f"{'-':>6s} {'-':>9s}"
            print(
                f"{name:44s} {seconds:7.2f} {fps:9.1f} {fps / FPS:10.2f} {1000 * seconds / n:9.2f} {e}",
                flush=True,
            )

        s, _ = timed(lambda: sum(1 for _ in iter_frames(video)), args.repeats)
        row("decode only", s)
        s, _ = timed(lambda: sum(1 for _ in iter_frames(video, prefetch=4)), args.repeats)
        row("decode only, prefetch thread", s)

        frames = [f.image for f in iter_frames(video, end_s=min(n, 30) / FPS)]

        def crops_only():
            for i, img in enumerate(frames):
                for b in boxes[i]:
                    cut_crop(img, crop_window(b, 256))

        s, _ = timed(crops_only, args.repeats)
        print(
            f"{'  crops alone (256 px, per detection)':44s} {1000 * s / (len(frames) * args.people):7.2f} ms"
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
                return track_video(
                    video,
                    out,
                    det,
                    BoxDepthPredictor(),
                    model={"name": "box-depth", "version": "0"},
                    camera=camera,
                    options=options,
                    resume=False,
                )

            s, res = timed(run, args.repeats)
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

            s, res = timed(run_gst, args.repeats)
            row(name, s, errors(res.path, boxes))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
