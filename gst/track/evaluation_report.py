"""Track evaluations written for people: one JSON per video, one markdown table across videos."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from gst.atomic import atomic_write, finite_json
from gst.track.evaluate import TrackEvaluation

__all__ = ["evaluation_markdown", "write_evaluation_json", "write_evaluation_markdown"]


def write_evaluation_json(evaluation: TrackEvaluation, path: str | Path) -> Path:
    """`evaluation` as JSON at `path` (atomic); undefined rates (no truth, no rows) are null."""
    path = Path(path)
    text = json.dumps(finite_json(evaluation.to_dict()), indent=2, allow_nan=False)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text + "\n"))
    return path


def _fmt(value, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def evaluation_markdown(
    evaluations: Sequence[TrackEvaluation], title: str = "Track evaluation"
) -> str:
    """A markdown report: one row per video, then per truth person, with the definitions' link."""
    lines = [
        f"# {title}",
        "",
        "Tracked rows matched to the synthetic truth per frame (Hungarian on box IoU); "
        "definitions in docs/track_evaluation.md. Errors in mm over matched rows; MPJPE is "
        "pelvis-aligned, root error is the absolute world pelvis error.",
        "",
        "| video | frames | recall | recall, half visible | precision | MOTA | IDF1 | "
        "id switches | fragments | ids/person | MPJPE | PA-MPJPE | root mean | root median | "
        "mirrored rows | MPJPE, not mirrored |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in evaluations:
        lines.append(
            f"| {e.video} | {e.frames} | {_fmt(e.recall, 3)} | {_fmt(e.recall_half_visible, 3)} | "
            f"{_fmt(e.precision, 3)} | {_fmt(e.mota, 3)} | {_fmt(e.idf1, 3)} | {e.id_switches} | "
            f"{e.fragments} | {_fmt(e.ids_per_person, 2)} | "
            f"{_fmt(e.mpjpe_mm)} | {_fmt(e.pa_mpjpe_mm)} | {_fmt(e.root_error_mm)} | "
            f"{_fmt(e.root_error_median_mm)} | {e.mirrored_rows} | "
            f"{_fmt(e.mpjpe_mm_not_mirrored)} |"
        )
    if evaluations:
        total_sw = sum(e.id_switches for e in evaluations)
        lines += ["", f"Total id switches: {total_sw} over {len(evaluations)} video(s)."]
    lines += [
        "",
        "## Per truth person",
        "",
        "| video | person | visible | matched | track ids | id switches | fragments | MPJPE | "
        "PA-MPJPE | root |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in evaluations:
        for p in e.persons:
            ids = ", ".join(str(i) for i in p.track_ids) or "-"
            lines.append(
                f"| {e.video} | {p.truth_person_id} | {p.frames_visible} | {p.frames_matched} | "
                f"{ids} | {p.id_switches} | {p.fragments} | {_fmt(p.mpjpe_mm)} | "
                f"{_fmt(p.pa_mpjpe_mm)} | {_fmt(p.root_error_mm)} |"
            )
    return "\n".join(lines) + "\n"


def write_evaluation_markdown(evaluations: Sequence[TrackEvaluation], path: str | Path) -> Path:
    """`evaluation_markdown(evaluations)` written atomically to `path`."""
    path = Path(path)
    text = evaluation_markdown(evaluations)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))
    return path
