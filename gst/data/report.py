"""Human-readable extraction report: markdown summary and a contact sheet of crops with masks."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gst.atomic import atomic_path, atomic_write_text
from gst.data.extract import ExtractReport
from gst.data.store import CropStore

_PALETTE = [  # BGR, told apart at a glance; given to the ids in the order they sort
    (60, 200, 60),
    (60, 60, 230),
    (230, 140, 40),
    (200, 60, 200),
    (40, 200, 220),
    (200, 200, 60),
    (255, 255, 255),
    (40, 120, 255),
    (150, 90, 40),
    (120, 255, 180),
    (180, 130, 255),
    (0, 160, 160),
]


def overlay_mask(
    image: np.ndarray, mask: np.ndarray, color: tuple[int, int, int], alpha: float = 0.35
) -> np.ndarray:
    """Tint the masked part of a BGR crop and outline it (mask: 0..255 coverage)."""
    out = image.astype(np.float32)
    a = (mask.astype(np.float32) / 255.0)[..., None] * alpha
    out = out * (1 - a) + np.array(color, dtype=np.float32) * a
    out = out.clip(0, 255).astype(np.uint8)
    contours, _ = cv2.findContours(
        (mask >= 128).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )
    cv2.drawContours(out, contours, -1, color, 1, lineType=cv2.LINE_AA)
    return out


def id_colours(ids) -> dict[int, tuple[int, int, int]]:
    """A palette colour per distinct id, in the order the ids sort."""
    return {pid: _PALETTE[k % len(_PALETTE)] for k, pid in enumerate(sorted(set(ids)))}


def contact_sheet(store: CropStore, rows: int = 10, tile: int = 144) -> np.ndarray:
    """A grid image: one row per sampled (frame, person), one column per camera."""
    groups = store.multiview_groups(min_views=1)
    names = store.camera_names
    head, left = 24, 90
    if not groups:
        sheet = np.full((head + tile, left + tile * max(1, len(names)), 3), 40, np.uint8)
        cv2.putText(
            sheet,
            "no crops",
            (8, head + tile // 2),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (255, 255, 255),
            1,
        )
        return sheet
    # Spread the sample over time and over people.
    pick = np.unique(np.linspace(0, len(groups) - 1, min(rows, len(groups))).round().astype(int))
    chosen = [groups[i] for i in pick]
    # a colour per id of the store (ids 2 and 8 shared one by id % 6, and a split person read
    # as one); more ids than colours reuse them
    colour = id_colours(g.person_id for g in groups)
    sheet = np.full((head + tile * len(chosen), left + tile * len(names), 3), 32, np.uint8)
    for j, n in enumerate(names):
        cv2.putText(
            sheet,
            n[:14],
            (left + j * tile + 4, 17),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (255, 255, 255),
            1,
        )
    for i, g in enumerate(chosen):
        y = head + i * tile
        color = colour[g.person_id]
        cv2.putText(
            sheet, f"f{g.frame}", (4, y + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1
        )
        cv2.putText(
            sheet, f"id {g.person_id}", (4, y + 42), cv2.FONT_HERSHEY_SIMPLEX, 0.5, color, 1
        )
        batch = store.read(g.indices)
        for k, cam in enumerate(g.cameras):
            crop = overlay_mask(batch.images[k], batch.masks[k], color)
            crop = cv2.resize(crop, (tile - 2, tile - 2), interpolation=cv2.INTER_AREA)
            x = left + int(cam) * tile
            sheet[y + 1 : y + tile - 1, x + 1 : x + tile - 1] = crop
    return sheet


def _table(header: tuple[str, ...], rows: list[tuple]) -> list[str]:
    """Markdown lines of a table after a blank line: the first column left-aligned, the others
    right-aligned, each value through `_fmt`."""
    out = ["", "| " + " | ".join(header) + " |", "| --- |" + " ---: |" * (len(header) - 1)]
    return out + ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in rows]


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


@dataclass(frozen=True)
class ExtractReportFiles:
    """The files `write_extract_report` wrote."""

    markdown: Path
    json: Path
    contact_sheet: Path


def write_extract_report(
    report: ExtractReport, store_path: Path | str, out_dir: Path | str, name: str = "extract"
) -> ExtractReportFiles:
    """Write `<name>.md`, `<name>.json` and `<name>_contact_sheet.png` into `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    store = CropStore(store_path)
    sheet_path = out_dir / f"{name}_contact_sheet.png"
    with atomic_path(sheet_path) as tmp:
        if not cv2.imwrite(str(tmp), contact_sheet(store)):
            raise OSError(f"could not write {sheet_path}")
    support = store.index.column("mask_support").to_numpy() if len(store) else np.zeros(0)
    support = support[np.isfinite(support)]
    store.close()

    r = report
    lines = [
        f"# Extraction report: {Path(r.store).name}",
        "",
        f"- frames: {r.frames_total} in the videos, {r.frames_considered} considered "
        f"(stride {r.frame_stride}), "
        f"{r.frames_with_people} with people, {r.frames_skipped_empty} skipped (nobody found)",
        f"- crops: {r.crops}; distinct person ids: {r.persons}; "
        "(frame, person) groups seen by >= 2 cameras: "
        f"{r.multiview_groups}",
        f"- cameras that saw no one (skipped): {', '.join(r.cameras_skipped) or 'none'}",
        f"- (frame, camera) pairs already done and resumed: {r.pairs_resumed}",
        f"- association: {r.association_method}; single-view crops (one camera saw the person): "
        f"{r.single_view_crops}",
    ]
    if len(support):
        q = np.percentile(support, [10, 50, 90])
        lines.append(
            "- mask support (hull: share of the person's 3D hull the mask covers; keypoints: "
            "share of the body not hidden by others; low = partial mask): "
            f"10% {q[0]:.3f}, median {q[1]:.3f}, 90% {q[2]:.3f}; "
            f"{int((support < 0.5).sum())} crops below 0.5"
        )
    if r.short_tracks_dropped:
        lines.append(f"- ids seen too briefly to crop (dropped): {r.short_tracks_dropped}")
    if r.crops_scored:
        lines += [
            f"- truth: mean mask IoU {_fmt(r.mask_iou)}, "
            f"association accuracy {_fmt(r.association_accuracy)} "
            f"over {r.crops_scored} crops; truth views {r.truth_views}, "
            f"missed {r.truth_views_missed}",
        ]
        if r.visible_views:
            lines.append(
                f"- truth views with >= 30% of the person's joints visible: {r.visible_views}, "
                f"missed {r.visible_views_missed}"
            )
    if any(r.truth_by_source):  # the keypoint path names its views' sources; the hull does not
        lines += _table(
            ("view source", "crops", "mask IoU", "association of the other crops"),
            [
                (source or "hull", sc.crops, sc.mask_iou, sc.association_without)
                for source, sc in r.truth_by_source.items()
            ],
        )
    if r.truth_by_id:
        lines += _table(
            ("id", "frames", "crops by truth person (0: nobody)"),
            [
                (pid, "-".join(map(str, v["frames"])),
                 ", ".join(f"{t}: {n}" for t, n in v["truth"].items()))
                for pid, v in r.truth_by_id.items()
            ],
        )  # fmt: skip
    lines += _table(
        ("camera", "crops", "frames with people", "frames without", "mask IoU", "masks s",
         "crops s"),
        [
            (cam, c.crops, c.frames_with_people, c.frames_without_people, c.mask_iou,
             f"{c.seconds_masks:.1f}", f"{c.seconds_crops:.1f}")
            for cam, c in r.per_camera.items()
        ],
    )  # fmt: skip
    lines += [
        "",
        "Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in r.timings.items()),
        "",
        f"![contact sheet]({sheet_path.name})",
        "",
    ]
    md_path = out_dir / f"{name}.md"
    json_path = out_dir / f"{name}.json"
    for path, text in (
        (md_path, "\n".join(lines)),
        (json_path, json.dumps(r.to_dict(), indent=1, default=str)),
    ):
        atomic_write_text(path, text)
    return ExtractReportFiles(markdown=md_path, json=json_path, contact_sheet=sheet_path)
