"""Small real stages used by the pipeline tests: they read inputs and write files."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from pydantic import Field

from gst.param_types import NAMES_FILE
from pipeline.stage import Stage, StageContext, StageParams


class SourceParams(StageParams):
    value: int = 1
    input_file: str | None = Field(None, json_schema_extra=NAMES_FILE)  # a name or a file
    label: str = "median"  # a plain text: never a path
    extra_file: Path | None = None  # a path parameter: relative to the config's folder
    torch_threads: int = 0  # > 0: set torch's (process-wide) thread count, as some stages do


def _own_folder_stage(name: str, run, **kwargs) -> Stage:
    """A stage whose one output is the folder named after it."""
    return Stage(name=name, run=run, outputs=lambda ctx: [name], **kwargs)


def _source(ctx: StageContext) -> None:
    if ctx.params.torch_threads:
        import torch

        torch.set_num_threads(ctx.params.torch_threads)
    text = f"value={ctx.params.value}\n"
    if ctx.params.input_file:
        text += Path(ctx.params.input_file).read_text()
    if ctx.params.extra_file:
        text += ctx.params.extra_file.read_text()
    ctx.out("source/data.txt").write_text(text)
    _bump_counter(ctx, "source")


def _bump_counter(ctx: StageContext, name: str) -> None:
    counter = os.environ.get("FAKE_STAGE_COUNTER")
    if counter:
        with open(counter, "a") as f:
            f.write(name + "\n")


SOURCE = _own_folder_stage(
    "source",
    _source,
    params_model=SourceParams,
    inputs=lambda ctx: [Path(ctx.params.input_file)] if ctx.params.input_file else [],
    help="writes source/data.txt",
)


class DoubleParams(StageParams):
    factor: int = 2
    die_after_partial_write: bool = False


def _double(ctx: StageContext) -> None:
    data = ctx.path("source/data.txt").read_text()
    out = ctx.out("double/result.txt")
    with open(out, "w") as f:
        f.write(data * ctx.params.factor)
        f.flush()
        if ctx.params.die_after_partial_write:
            os.kill(os.getpid(), signal.SIGKILL)
            time.sleep(10)
    _bump_counter(ctx, "double")


DOUBLE = _own_folder_stage(
    "double", _double, params_model=DoubleParams, help="repeats the source text"
)


def _report(ctx: StageContext) -> None:
    ctx.out("reports/summary.txt").write_text(str(len(ctx.path("double/result.txt").read_text())))
    _bump_counter(ctx, "report")


REPORT = Stage(
    name="report",
    run=_report,
    outputs=lambda ctx: ["reports/summary.txt"],
    help="counts characters",
)


class FailParams(StageParams):
    message: str = "boom"
    bad_input: bool = False  # fail as a stage fails on a corrupt video, not on a bug


def _fail(ctx: StageContext) -> None:
    from gst.video import VideoError

    ctx.out("fail/partial.txt").write_text("half")
    raise (VideoError if ctx.params.bad_input else RuntimeError)(ctx.params.message)


FAIL = _own_folder_stage("fail", _fail, params_model=FailParams)


def _no_output(ctx: StageContext) -> None:
    ctx.out("elsewhere.txt").write_text("not the declared output")


NO_OUTPUT = _own_folder_stage("nothing", _no_output)


class FanOutParams(StageParams):
    seconds: float = 0.0  # each item sleeps this long
    marker_dir: str | None = None  # each item writes its pid here first


def fan_out_item(item: tuple[int, float, str]) -> int:
    """A worker's job: record its pid, sleep, return the item."""
    k, seconds, marker_dir = item
    if marker_dir:
        Path(marker_dir, f"worker-{k}.pid").write_text(str(os.getpid()))
    time.sleep(seconds)
    return k


def _fan_out(ctx: StageContext) -> None:
    p = ctx.params
    items = [(k, p.seconds, p.marker_dir) for k in range(2)]
    done = ctx.executor.map(fan_out_item, items, description="fan out")
    ctx.out("fanout/done.txt").write_text(",".join(map(str, done)))


FANOUT = _own_folder_stage(
    "fanout", _fan_out, params_model=FanOutParams, help="two items through the executor"
)


def _constant(ctx: StageContext) -> None:
    ctx.path("source/data.txt").read_text()  # reads it, writes the same bytes whatever it holds
    ctx.out("constant/ok.txt").write_text("ok\n")
    _bump_counter(ctx, "constant")


CONSTANT = _own_folder_stage("constant", _constant, help="the same output whatever the source")


def _peek(ctx: StageContext) -> None:
    """Reads an ancestor's output (source, through constant), as extract reads synth's videos."""
    ctx.out("peek/copy.txt").write_text(ctx.path("source/data.txt").read_text())
    _bump_counter(ctx, "peek")


PEEK = _own_folder_stage("peek", _peek, help="copies the source's data, needing only constant")


def _sceneless(ctx: StageContext) -> None:
    """Writes what it would write for any scene (as pretrain trains on worlds of its own)."""
    ctx.out("sceneless/weights.txt").write_text("w\n")
    _bump_counter(ctx, "sceneless")


SCENELESS = _own_folder_stage(
    "sceneless", _sceneless, reads_scene=False, help="reads nothing of the scene"
)


def _extras(ctx: StageContext) -> None:
    ctx.out("extras/main.txt").write_text("main\n")
    if ctx.options.get("with_gaussians"):
        ctx.out("extras/splats/one.ply").write_text("ply\n")
    _bump_counter(ctx, "extras")


EXTRAS = Stage(
    name="extras",
    run=_extras,
    outputs=lambda ctx: (
        ["extras/main.txt"] + (["extras/splats"] if ctx.options.get("with_gaussians") else [])
    ),
    cli_options=("with_gaussians",),
    help="an output only with --with-gaussians, as track's splats",
)


def _per_video(ctx: StageContext) -> None:
    ctx.out("per_video/out.txt").write_text(f"{ctx.options.get('video')}\n")


PER_VIDEO = Stage(
    name="per_video",
    run=_per_video,
    outputs=lambda ctx: ["per_video/out.txt"],
    variant=lambda ctx: ctx.options.get("video"),
    cli_options=("video",),
    help="one record per --video, as track's",
)


def fail_first_item(item: tuple[int, str]) -> int:
    """An executor item: item 0 fails at once, the others take a second and leave a file in the
    folder given with them (how many ran after the failure)."""
    index, folder = item
    if index == 0:
        time.sleep(0.2)
        raise ValueError("item 0 is bad")
    time.sleep(1.0)
    Path(folder, f"ran_{index}").write_text("ran")
    return index


class TwoArgumentError(Exception):
    """Pickles in a worker but cannot be rebuilt from its args (no `__reduce__`)."""

    def __init__(self, path: str, why: str):
        super().__init__(f"{path}: {why}")


def fail_with_two_arguments(item: int) -> int:
    """An executor item: item 1 raises an error that cannot cross back to the parent as is."""
    if item == 1:
        raise TwoArgumentError("cam01.mp4", "the lens model is unknown")
    return item


def mark_and_sleep(item: tuple[int, str]) -> int:
    """An executor item that leaves a file in the folder given with it as it starts, then takes
    four seconds (which items a stopped map still started)."""
    index, folder = item
    Path(folder, f"started_{index}").write_text("started")
    time.sleep(4.0)
    return index


REAL_ONLY = _own_folder_stage(
    "real_only",
    lambda ctx: _bump_counter(ctx, "real_only"),
    applies=lambda scene: not scene.is_synthetic,
    help="does not apply to synthetic scenes (as bench does not apply to scenes without truth)",
)
