"""`python -m pipeline`: run stages, show their status.

Exit codes: 0 ok, 1 a stage failed (the message names the stage and the cause), 2 bad
config or arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import os
import re
import sys
import textwrap
from pathlib import Path

from rich.table import Table

from gst.atomic import remove_path
from pipeline.config import PipelineConfig, load_config, scene_input_problems
from pipeline.console import ProgressBars, make_console, print_error, setup_logging
from pipeline.dag import upstream_closure
from pipeline.errors import ConfigError, PipelineError
from pipeline.executors import make_executor
from pipeline.param_help import field_comments
from pipeline.registry import load_stages
from pipeline.runner import KEPT, MISSING, SKIPPED, STALE, UP_TO_DATE, Runner

EPILOG = """examples:
  python -m pipeline run all                      run every stale stage of the default scene
  python -m pipeline run calibrate --scene lab    calibrate the 'lab' scene (and what it needs)
  python -m pipeline run train --set train.steps=200
  python -m pipeline run track --video match.mp4
  python -m pipeline status                       which stages are up to date, and why not
  torchrun --nproc_per_node 2 -m pipeline run train   train with DDP on 2 processes \
(GPUs or CPU/gloo)
"""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        default="pipeline.yaml",
        type=Path,
        help="pipeline file (default: ./pipeline.yaml)",
    )
    p.add_argument(
        "--scene", action="append", help="scene name (repeatable, or 'all'; default: default_scene)"
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="STAGE.KEY=VALUE",
        help="override a stage parameter (value parsed as YAML), e.g. --set train.steps=200",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or info logs")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse exits 2 too; keep its message but use our format
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="python -m pipeline",
        description=__doc__.split("\n\n")[0],
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    run = sub.add_parser(
        "run",
        help="run a stage (after the upstream stages whose outputs are missing; stale ones are "
        "kept, --upstream reruns them), or 'all'",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EPILOG,
    )
    run.add_argument(
        "stage",
        help="stage name, or 'all'; the project's pipeline.yaml declares synth, calibrate, "
        "extract, fuse, pretrain, train, track, evaluate, bench (`python -m pipeline stages` "
        "lists a config's own with what each does)",
    )
    _common(run)
    run.add_argument(
        "--force",
        action="store_true",
        help="rerun the named stage even if it is up to date (with 'all': every stage of "
        "`run all`, pretrain included)",
    )
    run.add_argument("--force-all", action="store_true", help="rerun every stage in the plan")
    run.add_argument("--dry-run", action="store_true", help="print the plan and why, run nothing")
    run.add_argument(
        "--upstream",
        action="store_true",
        help="also rerun stale upstream stages whose outputs exist (default: use those outputs "
        "and say so; missing ones always run)",
    )
    run.add_argument("--executor", choices=["local", "ray"], help="override executor.kind")
    run.add_argument("--workers", type=_at_least_one, help="override executor.workers (>= 1)")
    run.add_argument("--ray-address", help="address of an existing Ray cluster")
    track = run.add_argument_group("track options")
    track.add_argument(
        "--video", action="append", type=Path, help="video file to track (repeatable)"
    )
    track.add_argument(
        "--with-gaussians", action="store_true", help="also export a splat PLY per track"
    )

    status = sub.add_parser("status", help="show which stages are up to date, stale or missing")
    _common(status)

    stages = sub.add_parser("stages", help="list the declared stages and what they do")
    stages.add_argument(
        "--params", action="store_true",
        help="also list each stage's parameters: default, and the value the pipeline file (or "
        "--set) gives the stage; with --scene, the values that scene's own params give it",
    )  # fmt: skip
    _common(stages)
    return parser


def _param_lines(model, configured: dict, scenes: dict[str, dict] | None = None) -> list[str]:
    """One line per parameter of a stage's params model: name, type, default, the value the
    pipeline file (with any --set) gives the stage, and the values `scenes` (scene name -> that
    scene's own params for the stage) give it, which win where set."""
    lines = []
    comments = field_comments(model)
    for key, field in model.model_fields.items():
        t = field.annotation
        kind = t.__name__ if isinstance(t, type) else str(t).replace("typing.", "")
        # PositiveInt | None prints as Optional[Annotated[int, Gt(gt=0)]]: int | None (a
        # Field(...) prints its metadata in brackets too: tuple[Annotated[float, Field(gt=5)], ...])
        kind = re.sub(r"Annotated\[(\w+), (?:[^\[\]]|\[[^\[\]]*\])*\]", r"\1", kind)
        kind = re.sub(r"^Optional\[(.*)\]$", r"\1 | None", kind)
        default = field.get_default(call_default_factory=True)
        line = f"{key}: {kind} = {default!r}"
        if key in configured:
            line += f"  (pipeline file: {configured[key]!r})"
        for scene, params in (scenes or {}).items():
            if key in params:
                line += f"  (scene {scene}: {params[key]!r})"
        lines.append(line)
        if key in comments:
            lines += textwrap.wrap(
                comments[key], 92, initial_indent="    ", subsequent_indent="    "
            )
    return lines


def _check_videos_option(videos: list[Path], probe: bool = False) -> list[Path]:
    """`--video` files must exist, and their names (file stems, which name the tracks) must
    differ: two files called clip.mp4 would overwrite each other's tracks. `probe`: each must
    open as a video too (for `track`)."""
    folders = [str(v) for v in videos if v.is_dir()]
    if folders:
        raise ConfigError(f"--video: a folder, not a video file: {', '.join(folders)}")
    missing = [str(v) for v in videos if not v.is_file()]
    if missing:  # the folder it was looked for in, for a path typed relative to another one
        raise ConfigError(
            f"--video: no such file: {', '.join(missing)} (looked for from {Path.cwd()})"
        )
    # one file under two paths (a linked folder, a relative and an absolute path) too
    resolved = [v.resolve() for v in videos]
    twice = list(
        dict.fromkeys(
            str(v) for v, r in zip(videos, resolved, strict=True) if resolved.count(r) > 1
        )
    )  # in the order given
    if twice:
        raise ConfigError(
            f"--video: one file listed twice: {', '.join(twice)}; remove the duplicate"
        )
    from gst.video import VideoError, probe_video, still_image_error

    errors = []
    for v in videos if probe else ():  # failed inside track, after the stages before it ran
        try:
            if (image := still_image_error(v)) is not None:
                raise VideoError(image)
            probe_video(v)
        except VideoError as exc:  # every broken file named at once, not one per rerun
            errors.append(str(exc))
    if errors:  # a data error (exit 1), as when track itself finds it
        raise PipelineError("--video: " + "\n--video: ".join(errors))
    from gst.track.writer import partition_name

    by_name: dict[str, list[str]] = {}
    for v in videos:
        try:
            partition_name(v.stem)
        except ValueError as exc:
            raise ConfigError(f"--video: {v}: {exc}") from None
        by_name.setdefault(v.stem, []).append(str(v))
    clashes = {n: paths for n, paths in by_name.items() if len(paths) > 1}
    if clashes:
        detail = "; ".join(f"'{n}': {', '.join(p)}" for n, p in clashes.items())
        raise ConfigError(
            f"--video: tracks are named after the file name, and these share one ({detail}); "
            "rename or link one of them under another name"
        )
    return videos


def _tracks_of_another_file(
    cfg: PipelineConfig, scenes: list[str], videos: list[Path]
) -> list[str]:
    """The `--video` files whose tracks folder (named after the file name) already holds the
    tracks of another file: `day1/match.mp4`, then `day2/match.mp4`, replaced the first's tracks
    without a word. The same file moved (same content) is not another file."""
    from gst.track.read import read_metadata
    from gst.track.writer import FINAL_NAME, partition_dir
    from gst.video import content_digest

    clashes = []
    for scene in scenes:
        for v in videos:
            existing = cfg.scene_workspace(scene) / partition_dir("tracks", v.stem) / FINAL_NAME
            if not existing.is_file():
                continue
            try:
                before = read_metadata(existing).get("video") or {}
            except (ValueError, OSError):
                continue  # unreadable: the stage reports it
            if before.get("content_sha256") in (None, content_digest(v)):
                continue  # the same video (moved or not), or a file too old to tell
            clashes.append(
                f"{existing.parent} holds the tracks of another video called "
                f"{before.get('file', v.name)} (other content than {v})"
            )
    return clashes


def _did_you_mean(name: str, names) -> str:
    """' (did you mean 'train'?)' for a typo of one of `names` (`run trian`), else ''."""
    close = difflib.get_close_matches(name, list(names), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _scenes(cfg: PipelineConfig, requested: list[str] | None) -> list[str]:
    if requested and "all" in requested:
        return list(cfg.scenes)
    if requested:
        unknown = [s for s in requested if s not in cfg.scenes]
        if unknown:
            raise ConfigError(
                f"--scene: unknown scene(s) {unknown}{_did_you_mean(unknown[0], cfg.scenes)} "
                f"(scenes: {sorted(cfg.scenes)})"
            )
        return list(dict.fromkeys(requested))  # `--scene demo --scene demo`: once
    if cfg.default_scene:
        return [cfg.default_scene]
    if len(cfg.scenes) == 1:
        return list(cfg.scenes)
    raise ConfigError(
        f"several scenes are declared ({sorted(cfg.scenes)}): pass --scene NAME or set "
        "default_scene"
    )


_STYLE = {UP_TO_DATE: "green", STALE: "yellow", MISSING: "red", SKIPPED: "dim", KEPT: "yellow"}


def _status_table(title: str, statuses) -> Table:
    table = Table(title=title, title_justify="left")
    table.add_column("stage")
    table.add_column("state")
    table.add_column("reason", overflow="fold")  # wrapped, not cut: the path's end is its name
    for st in statuses:
        table.add_row(st.key, f"[{_STYLE.get(st.state, '')}]{st.state}[/]", st.reason)
    return table


def _print_outputs(console, runner: Runner, planned) -> None:
    """Say where the results are: the outputs of every stage that ran or was up to date."""
    lines = []
    for st in planned:
        if st.state == SKIPPED:
            continue
        ctx = runner.context(st.stage)
        for rel in runner.stages[st.stage].outputs(ctx):
            lines.append(f"  {st.key:<12} {runner.workspace / rel}")
    if lines:
        console.print(
            f"outputs of scene '{runner.scene_name}':\n" + "\n".join(lines), highlight=False
        )


def _torchrun() -> tuple[int, int]:
    """(rank, world size) when launched by torchrun, else (0, 1)."""
    return int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))


def _distributed_plan(
    runner: Runner, targets: list[str], force: bool, force_all: bool
) -> list[str]:
    """Under torchrun every rank must take the same decision without talking first: run exactly
    the targets that are stale (or forced), and only once their upstream stages are up to date
    (rank 0 alone running, say, extract would leave the other ranks waiting at the rendezvous)."""
    done: dict = {}
    for name in upstream_closure(runner.needs, targets):
        done[name] = runner.status_of(name, done)  # no hash-cache save: rank 0 owns that file
    pending = [st.key for name, st in done.items() if name not in targets and st.needs_run]
    if pending:
        raise ConfigError(
            f"under torchrun the upstream stages must be up to date; run them first without "
            f"torchrun (python -m pipeline run {pending[-1]}); stale: {', '.join(pending)}"
        )
    return [
        name
        for name in targets
        if done[name].state != SKIPPED and (done[name].needs_run or force or force_all)
    ]


def _run_helper_rank(runner: Runner, stages: list[str], rank: int) -> None:
    """A non-zero torchrun rank: run the stage for its gradients only, in a private staging
    folder that is deleted afterwards. Rank 0 alone takes the lock, commits outputs and records
    the fingerprint (the Trainer also saves checkpoints and logs on rank 0 only)."""
    for name in stages:
        ctx = runner.context(name)
        ctx = dataclasses.replace(ctx, staging=runner.meta / "staging" / f"{name}.rank{rank}")
        remove_path(ctx.staging)
        ctx.staging.mkdir(parents=True)
        try:
            runner.stages[name].run(ctx)
        finally:
            remove_path(ctx.staging)


def _at_least_one(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return n


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    rank, world = _torchrun()
    if rank != 0:
        args.quiet = True  # one rank talks
    console = make_console(args.quiet)
    log_path = previous_sigterm = None
    try:
        cfg = load_config(args.config, args.overrides)
        stages = load_stages(cfg)
        scenes = _scenes(cfg, args.scene)
        if args.command == "stages":  # the listing is the command's output: stdout
            if args.params:  # the values `run` would refuse are not listed as set
                for scene in scenes:
                    Runner(cfg, scene, stages)
            out = make_console(False, stderr=False)  # the listing is the output, even with -q
            for name, st in stages.items():
                out.print(
                    f"[bold]{name}[/]  needs: {', '.join(cfg.stages[name].needs) or '-'}\n"
                    + "\n".join(textwrap.wrap(st.help, 96, initial_indent="    ",
                                               subsequent_indent="    ")),
                    highlight=False,
                    soft_wrap=True,
                )  # fmt: skip
                if args.params:
                    own = {  # a scene's own params, shown when the scenes were named
                        n: cfg.scenes[n].params.get(name) or {}
                        for n in (scenes if args.scene else [])
                    }
                    for line in _param_lines(st.params_model, cfg.stages[name].params, own):
                        out.print(f"      {line}", highlight=False, markup=False, soft_wrap=True)
            return 0
        progress = ProgressBars(console, enabled=not args.quiet)
        options, executor = {}, None
        if args.command == "run":
            if args.stage != "all" and args.stage not in cfg.stages:
                raise ConfigError(
                    f"unknown stage '{args.stage}'{_did_you_mean(args.stage, cfg.stages)} "
                    f"(stages: {', '.join(cfg.stages)}, or 'all')"
                )
            given = [o for o in ("video", "with_gaussians") if getattr(args, o)]
            reads = () if args.stage == "all" else stages[args.stage].cli_options
            unread = [o for o in given if args.stage != "all" and o not in reads]
            if unread:
                # `run calibrate --video x.mp4` ran the scene's calibrate without a word
                readers = [n for n in cfg.stages if unread[0] in stages[n].cli_options]
                raise ConfigError(
                    f"--{unread[0].replace('_', '-')} is not an option of '{args.stage}' (it is "
                    f"of: {', '.join(readers) or 'no stage'})"
                )
            tracks = args.stage == "track" or (args.stage == "all" and "track" in cfg.stages)
            options = {
                "video": [v.resolve() for v in _check_videos_option(args.video or [], tracks)],
                "with_gaussians": args.with_gaussians,
            }
            clashes = _tracks_of_another_file(cfg, scenes, options["video"])
            if clashes and not (args.force or args.force_all or args.dry_run):
                raise ConfigError(
                    "--video: tracks are named after the file name, and "
                    + "; ".join(clashes)
                    + ". Rename or link the new video under another name, or pass --force to "
                    "replace those tracks"
                )
            if args.ray_address and (args.executor or cfg.executor.kind) != "ray":
                raise ConfigError("--ray-address goes with the Ray executor: add --executor ray")
            if cfg.executor.ray_address and (args.executor or cfg.executor.kind) != "ray":
                # the local pool ran without a word where the file names a cluster
                raise ConfigError(
                    f"executor.ray_address ({cfg.executor.ray_address!r}) goes with the Ray "
                    f"executor, but the executor is '{args.executor or cfg.executor.kind}': set "
                    "executor.kind: ray (or add --executor ray), or remove executor.ray_address"
                )
            executor = make_executor(
                args.executor or cfg.executor.kind,
                args.workers or cfg.executor.workers,
                progress,
                ray_address=args.ray_address or cfg.executor.ray_address,
            )
        # Declared inputs that cannot exist stop a run before anything is written (status and
        # --dry-run show them instead: they are tools for a user whose inputs are broken).
        # (a scene's rig is an input only where the run reaches `calibrate`: `track` needs none)
        needs = {n: list(st.needs) for n, st in cfg.stages.items()}
        if args.command == "run" and args.stage != "all":
            rig = "calibrate" in upstream_closure(needs, [args.stage])
        else:
            rig = "calibrate" in needs
        # (globbed once: the status table and the dry run show the same lines)
        notes_of = {s: scene_input_problems(s, cfg.scenes[s], needs_rig=rig) for s in scenes}
        problems = [line for scene in scenes for line in notes_of[scene]]
        refused = problems if args.command == "run" and not args.dry_run else []
        # Build every runner first: it validates all stage params before anything is written.
        # (Said together with the inputs' problems: a wrong parameter was shown only once the
        # missing videos had been fixed, one round trip per kind of mistake.)
        try:
            runners = [
                Runner(cfg, scene, stages, options=options, executor=executor, progress=progress)
                for scene in scenes
            ]
        except ConfigError as exc:
            if refused:
                raise ConfigError("\n".join([*refused, str(exc)])) from exc
            raise
        if refused:
            raise ConfigError("\n".join(refused))
        if options.get("with_gaussians") and "track" in cfg.stages:
            for runner in runners:  # found inside the run, after the stages before track ran
                if getattr(runner.context("track").params, "chunk_frames", None):
                    raise ConfigError(
                        "--with-gaussians: chunked tracking (track.chunk_frames) cannot keep "
                        "per-person extras; turn chunking off for --with-gaussians"
                    )
        log_path = None
        if args.command == "run" and world > 1 and not args.dry_run:
            if args.stage == "all":
                raise ConfigError(
                    "under torchrun, name the stage to train (e.g. `run train`), not 'all'"
                )
            setup_logging(console, None, args.command, args.quiet)
            for runner in runners:
                todo = _distributed_plan(runner, [args.stage], args.force, args.force_all)
                if rank != 0:
                    _run_helper_rank(runner, todo, rank)
                elif todo:
                    runner.run(todo, force=True)
                else:
                    runner.run([args.stage])  # logs that it is up to date
            return 0
        if args.command == "run" and not args.dry_run:
            previous_sigterm = _stop_on_sigterm()
            log_path = setup_logging(
                console, cfg.workspace / ".pipeline" / "logs", args.command, args.quiet
            )
        else:
            setup_logging(console, None, args.command, args.quiet)
        for runner in runners:
            scene = runner.scene_name
            notes = notes_of[scene]
            report = make_console(False, stderr=False)  # the command's output: stdout
            if args.command == "status":
                report.print(
                    _status_table(f"scene '{scene}'  ({runner.workspace})", runner.status())
                )
                for note in notes:
                    report.print(f"[yellow]input problem:[/] {note}", highlight=False)
                continue
            targets = (
                [n for n in cfg.stages if stages[n].in_all] if args.stage == "all" else [args.stage]
            )
            planned = runner.run(
                targets,
                force=args.force,
                force_all=args.force_all,
                dry_run=args.dry_run,
                upstream=args.upstream,
            )
            if args.dry_run:
                report.print(_status_table(f"plan for scene '{scene}' (dry run)", planned))
                for note in notes:
                    report.print(f"[yellow]input problem:[/] {note}", highlight=False)
            else:
                _print_outputs(console, runner, planned)
        if log_path is not None and args.command == "run" and not args.quiet:
            console.print(f"log: {log_path}", highlight=False)
        return 0
    except PipelineError as exc:
        print_error(console, str(exc))
        _name_log(console, log_path)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        print_error(console, "terminated (SIGTERM)" if terminated else "interrupted")
        _name_log(console, log_path)
        return 143 if terminated else 130
    finally:
        if previous_sigterm is not None:  # main() called in a longer-lived process (tests)
            import signal

            signal.signal(signal.SIGTERM, previous_sigterm)


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill`, a scheduler's time limit), stopped as Ctrl-C stops a run: the stage is
    recorded as interrupted and resumes on the next run."""


def _stop_on_sigterm():
    """Turn SIGTERM in this process into `Terminated`. pycolmap's logging library installs a
    handler that prints a 40-line native stack dump, as a crash would; it does so when pycolmap
    is first imported, so it is imported now (a later import keeps the module and our handler).
    Worker processes forked from here die of SIGTERM as before (a pool's terminate sends it)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None  # only the main thread may set handlers
    import pycolmap  # noqa: F401

    main_pid = os.getpid()

    def handler(signum, frame):
        if os.getpid() != main_pid:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        raise Terminated()

    return signal.signal(signal.SIGTERM, handler)


def _name_log(console, log_path) -> None:
    """The run's log, which holds a failed stage's traceback (the error line alone was printed,
    and the file was found only by listing the logs folder)."""
    if log_path is not None:
        console.print(f"log (with the traceback): {log_path}", highlight=False, soft_wrap=True)


if __name__ == "__main__":
    sys.exit(main())
