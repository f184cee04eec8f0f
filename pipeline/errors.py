"""Exceptions that map to the CLI's exit codes (0 ok, 1 a stage failed, 2 bad config or args)."""

from pathlib import Path

# the project's packages: an error class of theirs that is a ValueError says what is wrong with
# an input (VideoError, RigFormatError, StoreError, ...), and the message names the culprit
OWN_PACKAGES = ("gst", "calibration", "synth", "pipeline", "stages")
PROJECT_ROOT = Path(__file__).resolve().parents[1]  # holds the packages above
# records of this logger go to the run's log file only, not the console: the traceback behind an
# input error, whose one-line message the CLI prints anyway
TRACEBACK_LOGGER = "pipeline.traceback"


def is_input_error(exc: BaseException) -> bool:
    """The stage stopped on bad or missing input, not on a bug: a file that is not there, or a
    ValueError that the project's own code raised (its own classes, or a plain ValueError whose
    message the project wrote: "videos ['cam04'] have no camera of that name"). Its message is
    what the user needs; the traceback only goes to the run's log file. A ValueError from inside
    a library (numpy's shapes) keeps its traceback: more likely a bug."""
    if isinstance(exc, FileNotFoundError):
        return True
    if not isinstance(exc, ValueError):
        return False
    return type(exc).__module__.split(".")[0] in OWN_PACKAGES or _raised_by_own_code(exc)


def _raised_by_own_code(exc: BaseException) -> bool:
    """Whether the innermost frame of `exc`'s traceback is a file of the project's packages."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is None:
        return False
    try:
        rel = Path(tb.tb_frame.f_code.co_filename).resolve().relative_to(PROJECT_ROOT)
    except ValueError:  # outside the project (a library in site-packages)
        return False
    return rel.parts[0] in OWN_PACKAGES


class PipelineError(Exception):
    """Base class for errors the CLI reports without a traceback."""

    exit_code = 1


class ConfigError(PipelineError):
    """The configuration or the command-line arguments are invalid (exit code 2)."""

    exit_code = 2


class StageFailed(PipelineError):
    """A stage raised; the message names the stage, the scene and the cause (exit code 1)."""

    exit_code = 1

    def __init__(self, stage: str, scene: str, cause: BaseException):
        self.stage, self.scene, self.cause = stage, scene, cause
        super().__init__(
            f"stage '{stage}' (scene '{scene}') failed: {type(cause).__name__}: {cause}"
        )

    def __reduce__(self):  # an executor's worker raising it: the parent rebuilds it
        return type(self), (self.stage, self.scene, self.cause)


class ItemFailed(RuntimeError):
    """An item of an executor's map could not be computed (its worker died, or, with Ray, it kept
    failing after its retries); the message names the item and why."""


def describe(item, limit: int = 200) -> str:
    """An item as error messages name it: its repr, cut to `limit` characters."""
    text = repr(item)
    return text if len(text) <= limit else text[:limit] + "..."
