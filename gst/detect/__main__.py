"""python -m gst.detect fetch [--models-dir DIR] [--from DIR] [--force]"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gst.detect.weights import MEDIAPIPE_WHEEL, default_models_dir, fetch_blazepose_models


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gst.detect",
        description="BlazePose person models for real footage (docs/person_models.md)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    fetch = sub.add_parser(
        "fetch",
        help=f"download {MEDIAPIPE_WHEEL.requirement}'s wheel from PyPI (not installed) "
        "and keep its two BlazePose models",
    )
    fetch.add_argument(
        "--models-dir",
        type=Path,
        default=None,
        help=f"where to keep them (default {default_models_dir()})",
    )
    fetch.add_argument(
        "--from",
        dest="archive_dir",
        type=Path,
        default=None,
        help=f"folder holding {MEDIAPIPE_WHEEL.filename} (no download)",
    )
    fetch.add_argument("--force", action="store_true", help="fetch again even if the files exist")
    args = parser.parse_args(argv)
    try:
        paths = fetch_blazepose_models(
            args.models_dir, archive_dir=args.archive_dir, force=args.force
        )
    except (RuntimeError, ValueError, FileNotFoundError) as exc:  # offline, a bad wheel
        print(
            f"error: {exc}\nOn a machine without PyPI: download {MEDIAPIPE_WHEEL.filename} "
            "elsewhere and run `python -m gst.detect fetch --from DIR` with it in DIR.",
            file=sys.stderr,
        )
        return 1
    for role, p in paths.items():
        print(f"{role}: {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
