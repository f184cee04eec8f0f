"""Command-line pieces shared by the benchmark scripts (they put the repository root on
sys.path)."""

from __future__ import annotations

import argparse


def bench_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's parser: its module docstring is the --help text, line breaks kept."""
    return argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )


def add_scene_size(ap: argparse.ArgumentParser, *, frames: int, people: int) -> None:
    """--frames and --people of the synthetic scene a benchmark makes."""
    ap.add_argument("--frames", type=int, default=frames)
    ap.add_argument("--people", type=int, default=people)
