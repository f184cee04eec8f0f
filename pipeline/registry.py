"""Find the `Stage` object behind each stage name declared in `pipeline.yaml`."""

from __future__ import annotations

import importlib

from pipeline.config import PipelineConfig
from pipeline.errors import ConfigError
from pipeline.stage import Stage


def load_stage(name: str, module: str | None = None) -> Stage:
    """Import `stages.<name>` (or the configured `module` / `module:ATTRIBUTE`) and return its
    `STAGE`."""
    module_name, _, attr = (module or f"stages.{name}").partition(":")
    attr = attr or "STAGE"
    try:
        mod = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        # the module itself (or a package above it) is missing; a module it imports is another
        # matter ('gait_stage' importing a helper that is not installed is not 'gait_stage'
        # missing: the names were compared as text, so 'gait' passed for 'gait_stage')
        if exc.name and (exc.name == module_name or module_name.startswith(exc.name + ".")):
            raise ConfigError(
                f"stages.{name}: no implementation found (module '{module_name}' does not exist)"
            ) from None
        raise ConfigError(
            f"stages.{name}: module '{module_name}' could not be imported: {exc} (is the "
            "package it needs installed?)"
        ) from exc
    stage = getattr(mod, attr, None)
    if not isinstance(stage, Stage):
        raise ConfigError(f"stages.{name}: module '{module_name}' defines no {attr} = Stage(...)")
    if stage.name != name:
        raise ConfigError(
            f"stages.{name}: module '{module_name}' defines stage '{stage.name}', not '{name}'"
        )
    return stage


def load_stages(cfg: PipelineConfig) -> dict[str, Stage]:
    return {name: load_stage(name, sc.module) for name, sc in cfg.stages.items()}
