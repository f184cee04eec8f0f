"""`stages --params` says what every stage parameter means, from the comments beside its field
(21 of 158 parameters were documented nowhere, and the listing gave none)."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from pipeline.cli import main
from pipeline.config import load_config
from pipeline.param_help import field_comments
from pipeline.registry import load_stages


class _Base(BaseModel):
    # two lines above
    # make one text
    a: int = 1
    b: int = 2  # trailing
    c: int = 3


class _Child(_Base):
    c: int = 4  # redeclared: the child's comment
    d: int = 5  # inside a default spread over lines
    e: int = 6


def test_comments_above_and_beside_a_field_are_its_help():
    assert field_comments(_Child) == {
        "a": "two lines above make one text",
        "b": "trailing",
        "c": "redeclared: the child's comment",
        "d": "inside a default spread over lines",
    }


def test_every_stage_parameter_of_the_shipped_pipeline_has_help(capsys, monkeypatch):
    shipped = Path(__file__).resolve().parents[1] / "pipeline.yaml"
    cfg = load_config(shipped)
    missing = [
        f"{name}.{field}"
        for name, stage in load_stages(cfg).items()
        for comments in [field_comments(stage.params_model)]
        for field in stage.params_model.model_fields
        if field not in comments
    ]
    assert missing == []
    monkeypatch.setenv("COLUMNS", "200")
    assert main(["stages", "--params", "--config", str(shipped)]) == 0
    out = capsys.readouterr().out
    assert "max_misses: int = 30" in out and "processed frames a person may go undetected" in out
