"""Exceptions that map to the CLI's exit codes (0 ok, 1 a stage failed, 2 bad config or args)."""


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
