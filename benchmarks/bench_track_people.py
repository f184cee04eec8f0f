"""Who the learned person model's loop keeps hold of: recall, MOTA and id switches of `track`'s
person model (gst.track.person_detector) on synthetic scenes' videos, against their truth.

Each scene's videos (`<workspace>/<scene>/synth/videos/*.mp4`, one per camera) are tracked with
the stage's tracker settings and the pixel-free BoxDepthPredictor (the network does not decide
who is tracked, so it is left out to keep the benchmark quick), then scored with
gst.track.evaluate (truth boxes from the scene's masks, Hungarian on box IoU >= 0.3; a miss
is a truth person with any visible pixel and no tracked box). Variants of the person model's
settings run in one process on the same videos; beside the scores, CPU milliseconds per frame of
the whole loop and detector runs per 100 frames.

Scenes are named as in `--workspace` (default workspace/; `synth` must have run for them): the
demo, and e.g. the crowd scenes of benchmarks/crowd_scenes.yaml (3-5 people who often stand
close). Tune on some scenes (`--tune`) and report the others: the means are printed for both
groups.

    python benchmarks/bench_track_people.py --workspace workspace \\
        --tune demo,crowd_dome_7000,crowd_h36m_7000 \\
        --report crowd_dome_7001,crowd_h36m_7001,crowd_dome_7002,crowd_h36m_7002
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import shutil
import tempfile
import time
from dataclasses import dataclass, replace

from benchmarks.cli import bench_parser
from calibration.formats import read_rig
from gst.track.baseline import BoxDepthPredictor
from gst.track.evaluate import evaluate_tracks
from gst.track.loop import TrackOptions, track_video
from gst.track.mirror import MirrorConfig
from gst.track.person_detector import PersonModelConfig, PersonModelDetector
from gst.track.scene import TrackSettings, person_model_config
from gst.track.tracker import TrackerConfig


@dataclass
class Score:
    frames: int = 0
    truth: int = 0
    matches: int = 0
    rows: int = 0
    switches: int = 0
    cpu_s: float = 0.0
    detector_runs: int = 0
    id_tp: int = 0  # identity true positives (gst.track.evaluate IDF1)
    half_visible: int = 0  # truth views with at least half their joints visible ...
    half_matched: int = 0  # ... and how many of them a tracked box matches
    mirrored: int = 0  # matched rows whose landmarks are left/right mirrored against the truth

    def __add__(self, o: Score) -> Score:
        return Score(*(a + b for a, b in zip(vars(self).values(), vars(o).values(), strict=True)))

    def line(self) -> str:
        recall = self.matches / max(self.truth, 1)
        precision = self.matches / max(self.rows, 1)
        errors = (self.truth - self.matches) + (self.rows - self.matches) + self.switches
        mota = 1 - errors / max(self.truth, 1)
        half = self.half_matched / max(self.half_visible, 1)
        idf1 = 2 * self.id_tp / max(self.truth + self.rows, 1)
        cpu_ms = 1000 * self.cpu_s / max(self.frames, 1)
        runs = 100 * self.detector_runs / max(self.frames, 1)
        return (
            f"recall {recall:.3f}  precision {precision:.3f}  MOTA {mota:.3f}  IDF1 {idf1:.3f}  "
            f"id switches {self.switches:3d}  half-visible recall {half:.3f}  "
            f"mirrored rows {self.mirrored:3d}/{self.matches}  "
            f"{cpu_ms:5.1f} CPU ms/frame  {runs:5.1f} detector runs/100 frames"
        )


def track_scene(
    scene_dir: Path, config: PersonModelConfig, options: TrackOptions, tmp: Path
) -> Score:
    total = Score()
    videos = sorted((scene_dir / "videos").glob("*.mp4"))
    if not videos:
        raise SystemExit(f"{scene_dir}/videos: no videos (run the scene's synth stage first)")
    # the scene's true cameras: the evaluation projects the truth joints with them to count
    # mirrored landmarks (the videos are tracked as uncalibrated, as before)
    rig = read_rig(scene_dir / "calibration" / "rig.json")
    for video in videos:
        out = tmp / "out"
        shutil.rmtree(out, ignore_errors=True)
        detector = PersonModelDetector(config)
        t0 = time.process_time()
        res = track_video(
            video,
            out,
            detector,
            BoxDepthPredictor(),
            model={"name": "box-depth", "version": "bench"},
            options=options,
            resume=False,
        )
        cpu = time.process_time() - t0
        ev = evaluate_tracks(res.path, scene_dir, video.stem, camera=rig[video.stem])
        total = total + Score(
            ev.frames, ev.truth_instances, ev.matches, ev.track_rows, ev.id_switches, cpu,
            detector.detector_runs, ev.id_true_positives, ev.half_visible,
            ev.half_visible_matched, ev.mirrored_rows,
        )  # fmt: skip
    return total


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--workspace", type=Path, default=Path("workspace"))
    ap.add_argument("--tune", default="demo", help="comma-separated scenes to tune on")
    ap.add_argument("--report", default="", help="comma-separated scenes to report on")
    ap.add_argument("--only", default=None, help="variants whose name has this text (a|b)")
    args = ap.parse_args()
    default = person_model_config(TrackSettings())
    stage_tracker = TrackerConfig(min_hits=3, max_misses=30)  # the track stage's
    stage = TrackOptions(tracker=stage_tracker, prefetch=0)

    def tracker(**kw) -> TrackOptions:
        return replace(stage, tracker=replace(stage_tracker, **kw))

    variants = [  # (name, person model settings, tracking options)
        ("stage default", default, stage),
        ("without the skeleton term (before)", default, tracker(w_skeleton=0.0)),
        ("skeleton term x2", default, tracker(w_skeleton=2.0)),
        ("skeleton term, scale 0.5", default, tracker(skeleton_scale=0.5)),
        ("detector every 5 frames", replace(default, detect_every=5), stage),
        ("detector every frame", replace(default, detect_every=1), stage),
        ("look-again overlap 1.0", replace(default, look_again_overlap=1.0), stage),
        ("lost people not looked for again (before)", replace(default, lost_retry=0), stage),
        ("lost people looked for 5 frames", replace(default, lost_retry=5), stage),
        ("lost people looked for 30 frames", replace(default, lost_retry=30), stage),
        ("doubted readings not continued (before)", replace(default, continue_distance=0), stage),
        ("doubted readings continued within 0.1", replace(default, continue_distance=0.1), stage),
        ("left/right labels as detected (before)", default, replace(stage, unmirror=None)),
        (
            "left/right: 0.5 s ahead, no end jump (before 12-01)",
            default,
            replace(stage, unmirror=MirrorConfig(lag_s=0.5, end_jump=False)),
        ),
        (
            "left/right: 0.5 s ahead, end jump",
            default,
            replace(stage, unmirror=MirrorConfig(lag_s=0.5)),
        ),
        (
            "left/right: prior 7.5/s (half)",
            default,
            replace(stage, unmirror=MirrorConfig(prior_per_s=7.5)),
        ),
        (
            "left/right: prior 30/s (double)",
            default,
            replace(stage, unmirror=MirrorConfig(prior_per_s=30.0)),
        ),
    ]
    if args.only:
        variants = [v for v in variants if any(o in v[0] for o in args.only.split("|"))]
    groups = {
        "tune": [s for s in args.tune.split(",") if s],
        "report": [s for s in args.report.split(",") if s],
    }
    tmp = Path(tempfile.mkdtemp(prefix="bench_track_people_"))
    try:
        for name, config, options in variants:
            print(f"\n{name}", flush=True)
            for group, scenes in groups.items():
                if not scenes:
                    continue
                total = Score()
                for scene in scenes:
                    score = track_scene(args.workspace / scene / "synth", config, options, tmp)
                    total = total + score
                    print(f"  {scene:18s} {score.line()}", flush=True)
                print(f"  {'= ' + group:18s} {total.line()}", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
