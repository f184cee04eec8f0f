"""Calibration report: markdown summary, a coverage image per camera and a 3D plot of the rig.

Plots use matplotlib's Agg canvas directly (no pyplot, no global backend switch), so the
module is safe to import anywhere, headless included.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from calibration.camera import Camera, Rig
from calibration.checks import CaptureVolume, check_rig, estimate_volume, lens_warnings
from calibration.solve import BoardCalibration
from gst.atomic import atomic_write, atomic_write_text

COVERAGE_GRID = (8, 6)  # cells across and down for the coverage percentage


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=110, bbox_inches="tight"))
    return path


def _imwrite_png(path: Path, image: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"cannot encode PNG for {path}")
    path.write_bytes(buf.tobytes())


def coverage_fraction(points: np.ndarray, width: int, height: int, grid=COVERAGE_GRID) -> float:
    """Fraction of image cells (grid across x down) holding at least one observation."""
    if len(points) == 0:
        return 0.0
    gx = np.clip((points[:, 0] / width * grid[0]).astype(int), 0, grid[0] - 1)
    gy = np.clip((points[:, 1] / height * grid[1]).astype(int), 0, grid[1] - 1)
    return len(set(zip(gx.tolist(), gy.tolist(), strict=True))) / (grid[0] * grid[1])


def plot_coverage(camera: Camera, inliers: np.ndarray, outliers: np.ndarray, path: Path) -> Path:
    """Detected board corners over the image frame (outliers in red)."""
    aspect = camera.height / camera.width
    fig = Figure(figsize=(6, max(2.5, 6 * aspect)))
    ax = fig.add_subplot(1, 1, 1)
    ax.add_patch(_rect(camera.width, camera.height))
    for points, what, style in (
        (inliers, "corners", dict(s=2, c="tab:blue", alpha=0.5)),
        (outliers, "outliers", dict(s=8, c="tab:red", marker="x")),
    ):
        if len(points):
            ax.scatter(points[:, 0], points[:, 1], label=f"{what} ({len(points)})", **style)
    ax.set_xlim(-0.02 * camera.width, 1.02 * camera.width)
    ax.set_ylim(1.02 * camera.height, -0.02 * camera.height)  # image y down
    ax.set_aspect("equal")
    cov = coverage_fraction(inliers, camera.width, camera.height)
    ax.set_title(f"{camera.name}: {camera.width}x{camera.height}, coverage {100 * cov:.0f}%")
    if len(inliers) or len(outliers):
        ax.legend(loc="upper right", fontsize=7)
    return _save(fig, path)


def _rect(w: int, h: int):
    from matplotlib.patches import Rectangle

    return Rectangle((-0.5, -0.5), w, h, fill=False, edgecolor="black", linewidth=1)


def _display_rotation(up) -> np.ndarray:
    """Rotation taking the rig's up axis to +z, for plotting."""
    up = np.asarray(up, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(up @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def plot_rig(
    rig: Rig,
    path: Path,
    volume: CaptureVolume | None = None,
    board_points: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """Camera poses in 3D and from above: frusta (the image's top edge drawn thick), names,
    optical axes, the floor (z = 0 of the up axis), world axes and the capture volume."""
    Rd = _display_rotation(rig.up)
    centers = np.array([c.center for c in rig]) @ Rd.T
    span = max(float(np.ptp(centers, axis=0).max()) if len(rig) > 1 else 1.0, 0.5)
    depth = 0.12 * span
    fig = Figure(figsize=(13, 6.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    pts = [centers, np.zeros((1, 3))]
    for cam, C in zip(rig, centers, strict=True):
        corners = (
            cam.unproject(
                np.array(
                    [
                        [0, 0],
                        [cam.width - 1, 0],
                        [cam.width - 1, cam.height - 1],
                        [0, cam.height - 1],
                    ],
                    dtype=float,
                ),
                depth,
            )
            @ Rd.T
        )
        axis_end = C + (Rd @ cam.optical_axis) * 0.6 * span
        for ax, dims in ((ax3, slice(0, 3)), (ax2, slice(0, 2))):
            for k in range(4):
                ax.plot(*np.stack([C, corners[k]])[:, dims].T, color="tab:blue", linewidth=0.8)
                ax.plot(
                    *np.stack([corners[k], corners[(k + 1) % 4]])[:, dims].T,
                    color="tab:blue",
                    linewidth=2.0 if k == 0 else 0.8,
                )  # edge 0-1 is the image's top
            ax.plot(
                *np.stack([C, axis_end])[:, dims].T,
                color="tab:orange",
                linewidth=0.7,
                linestyle="--",
            )
            ax.text(*C[dims], f" {cam.name}", fontsize=7)
        pts.append(corners)
    if volume is not None:
        corners_w = volume.corners()
        box = corners_w @ Rd.T
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(np.abs(corners_w[i] - corners_w[j]) > 1e-12) == 1:
                    ax3.plot(*np.stack([box[i], box[j]]).T, color="tab:green", linewidth=1)
                    ax2.plot(*np.stack([box[i], box[j]])[:, :2].T, color="tab:green", linewidth=1)
        pts.append(box)
    if board_points is not None and len(board_points):
        bp = np.asarray(board_points) @ Rd.T
        ax3.scatter(*bp.T, s=1, c="gray", alpha=0.2)
        ax2.scatter(*bp[:, :2].T, s=1, c="gray", alpha=0.2)
        pts.append(bp)
    allp = np.concatenate(pts)
    mid, half = (allp.max(0) + allp.min(0)) / 2, (allp.max(0) - allp.min(0)).max() / 2 * 1.05
    # Floor grid and world axes (x red, y green, up blue) at the origin.
    g = np.linspace(-half, half, 9)
    for v in g:
        ax3.plot(
            [mid[0] + v] * 2, [mid[1] - half, mid[1] + half], [0, 0], color="0.6", linewidth=0.5
        )
        ax3.plot(
            [mid[0] - half, mid[0] + half], [mid[1] + v] * 2, [0, 0], color="0.6", linewidth=0.5
        )
    for k, col in enumerate(("tab:red", "tab:green", "tab:blue")):
        e = np.zeros(3)
        e[k] = 0.15 * span
        ax3.plot(*np.stack([np.zeros(3), e]).T, color=col, linewidth=2)
        if k < 2:
            ax2.plot(*np.stack([np.zeros(2), e[:2]]).T, color=col, linewidth=2)
    ax3.set_xlim(mid[0] - half, mid[0] + half)
    ax3.set_ylim(mid[1] - half, mid[1] + half)
    z0 = min(float(allp[:, 2].min()), 0.0)  # keep the floor in view, at the bottom
    ax3.set_zlim(z0, z0 + 2 * half)
    ax3.set_box_aspect((1, 1, 1))
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("up (m)")
    ax2.set_aspect("equal")
    ax2.grid(True, linewidth=0.3)
    ax2.set_xlabel("x (m)")
    ax2.set_ylabel("y (m)")
    ax2.set_title("from above")
    fig.suptitle(
        title
        or f"{len(rig)} cameras (blue, thick edge = image top), optical axes (orange), "
        "capture volume (green), world axes x/y/up (red/green/blue)",
        fontsize=10,
    )
    return _save(fig, path)


def draw_world_overlay(
    camera: Camera,
    image: np.ndarray,
    extent: float = 3.0,
    step: float = 0.5,
    pole_height: float = 1.8,
) -> np.ndarray:
    """A copy of `image` with the floor grid (z = 0, every `step` m within +-`extent` m, yellow),
    the world axes (1 m; x red, y green, z blue) and a `pole_height` m pole at the origin
    (magenta) drawn through the camera: a visual check that a calibration fits its footage.
    Needs a z-up rig."""
    import cv2

    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    thick = max(1, round(max(out.shape[:2]) / 700))

    # Distortion polynomials misbehave far outside the image: keep points whose normalised
    # radius is within 1.2x that of the image corners.
    corners = np.array(
        [
            [0, 0],
            [camera.width - 1, 0],
            [0, camera.height - 1],
            [camera.width - 1, camera.height - 1],
        ],
        dtype=float,
    )
    r_max = 1.2 * np.linalg.norm(camera.undistort_points(corners), axis=1).max()

    def polyline(a, b, colour, width):
        pts = np.linspace(a, b, 200)
        pc = camera.to_camera(pts)
        ok = pc[:, 2] > 0.05
        ok[ok] = np.linalg.norm(pc[ok, :2] / pc[ok, 2:3], axis=1) < r_max
        pts = pts[ok]
        if len(pts) >= 2:
            uv = np.round(camera.project(pts)).astype(np.int32)
            cv2.polylines(out, [uv], False, colour, width, cv2.LINE_AA)

    for v in np.arange(-extent, extent + 1e-9, step):
        polyline((v, -extent, 0), (v, extent, 0), (0, 255, 255), thick)
        polyline((-extent, v, 0), (extent, v, 0), (0, 255, 255), thick)
    for k, colour in enumerate(((0, 0, 255), (0, 255, 0), (255, 0, 0))):
        e = np.zeros(3)
        e[k] = 1.0
        polyline(np.zeros(3), e, colour, 3 * thick)
    polyline(np.zeros(3), (0, 0, pole_height), (255, 0, 255), 2 * thick)
    return out


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _file_stems(names: list[str]) -> dict[str, str]:
    """A file-safe stem per camera name, unique within the rig: names that differ only in
    unsafe characters ('cam 1', 'cam_1') get their index appended, so no image overwrites
    another's."""
    safe = [_safe(n) for n in names]
    stems = [s if safe.count(s) == 1 else f"{s}-{i}" for i, s in enumerate(safe)]
    taken = set()
    for i, s in enumerate(stems):  # a stem that another name already is ('cam_1-1'): index it
        while s in taken:
            s = f"{s}-{i}"
        stems[i] = s
        taken.add(s)
    return dict(zip(names, stems, strict=True))


def _fmt(v: float, nd: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def write_calibration_report(
    rig: Rig,
    out_dir: str | Path,
    calibration: BoardCalibration | None = None,
    volume: CaptureVolume | tuple | None = None,
    frames: dict[str, np.ndarray] | None = None,
    appendix: list[str] | None = None,
) -> Path:
    """Write `calibration.md`, `coverage_<camera>.png` (board calibrations only),
    `camera_poses.png` and, given `frames` (camera name -> an image from that camera, z-up
    rigs), `overlay_<camera>.png` with the floor grid drawn in; returns the markdown path.

    `volume` is a CaptureVolume or (lo, hi); by default it is estimated for z-up rigs.
    `appendix`: markdown lines added at the end (e.g. a comparison with a known rig).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stems = _file_stems([cam.name for cam in rig])
    if volume is not None and not isinstance(volume, CaptureVolume):
        volume = CaptureVolume(*volume)
    if volume is None and np.allclose(rig.up, [0, 0, 1]):
        volume = estimate_volume(rig)
    board_pts = None
    if calibration is not None and calibration.world_from_board:
        obj = np.c_[calibration.board.object_points(), np.ones(calibration.board.n_corners)]
        board_pts = np.concatenate(
            [(T @ obj.T).T[:, :3] for T in calibration.world_from_board.values()]
        )
    plot_rig(rig, out / "camera_poses.png", volume, board_pts)

    lines = ["# Calibration report", ""]
    lines.append(
        f"{len(rig)} cameras; units m; up axis ({', '.join(f'{float(v):g}' for v in rig.up)}); "
        f"source: {rig.meta.get('source', 'unknown')}."
    )
    lines.append("")
    lines.append("![camera poses](camera_poses.png)")
    lines.append("")
    header = "| camera | size | fx | fy | cx | cy | k1 | k2 | centre x, y, z (m) |"
    sep = "|---|---|---|---|---|---|---|---|---|"
    if calibration is not None:
        header += " RMS px | initial RMS px | detections / frames | corners | outliers | coverage |"
        sep += "---|---|---|---|---|---|"
    lines += [header, sep]
    for cam in rig:
        d = np.zeros(2)
        d[: min(2, cam.dist.size)] = cam.dist[:2]
        c = cam.center
        row = (
            f"| {cam.name} | {cam.width}x{cam.height} | {cam.fx:.1f} | {cam.fy:.1f} | {cam.cx:.1f} "
            f"| {cam.cy:.1f} | {d[0]:.4f} | {d[1]:.4f} | {c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f} |"
        )
        if calibration is not None:
            n = cam.name
            obs = calibration.observations.get(n, np.zeros((0, 2)))
            cov = coverage_fraction(obs, cam.width, cam.height)
            row += (
                f" {_fmt(calibration.rms_px.get(n, np.nan), 3)} | "
                f"{_fmt(calibration.initial_rms_px.get(n, np.nan), 3)} | "
                f"{calibration.detections.get(n, 0)} / {calibration.frames_searched.get(n, '?')} | "
                f"{len(obs)} | {len(calibration.outliers.get(n, []))} | {100 * cov:.0f}% |"
            )
        lines.append(row)
    lines.append("")
    problems = check_rig(rig, volume)
    lines.append("## Checks")
    lines.append("")
    lines += [f"- warning: {w}" for w in lens_warnings(rig)]
    lines += [f"- {p}" for p in problems] or [
        "- all cameras above the floor and aimed into the capture volume"
        if volume is not None
        else "- no capture volume to check against"
    ]
    if volume is not None:
        lo, hi = (", ".join(f"{float(v):.2f}" for v in b) for b in (volume.lo, volume.hi))
        lines.append(f"- capture volume: ({lo}) to ({hi}) m")
    lines.append("")
    if calibration is not None:
        lines += [
            "## Board calibration",
            "",
            f"Board: {calibration.board.to_dict()}.",
            "",
            f"Overall RMS {calibration.rms_px_overall:.3f} px; world from the board on the floor "
            f"in frame {calibration.floor_frame}."
            if calibration.floor_frame is not None
            else f"Overall RMS {calibration.rms_px_overall:.3f} px; world = first camera.",
            "",
            "| step | seconds |",
            "|---|---|",
        ]
        lines += [f"| {k} | {v:.2f} |" for k, v in calibration.timings.items()]
        lines += [
            "",
            "| BA round | observations | RMS px | outlier limit px | removed | seconds |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['round']} | {r['observations']} | {r['rms_px']:.3f} | {r['limit_px']:.2f} | "
            f"{r['removed']} | {r['seconds']:.2f} |"
            for r in calibration.ba_rounds
        ]
        if calibration.notes:
            lines += ["", "Notes:", ""] + [f"- {n}" for n in calibration.notes]
        lines += ["", "## Coverage", ""]
        for cam in rig:
            name = f"coverage_{stems[cam.name]}.png"
            plot_coverage(
                cam,
                calibration.observations.get(cam.name, np.zeros((0, 2))),
                calibration.outliers.get(cam.name, np.zeros((0, 2))),
                out / name,
            )
            lines.append(f"![{cam.name}]({name})")
        lines.append("")
    if frames and np.allclose(rig.up, [0, 0, 1]):
        import cv2

        lines += [
            "## Floor grid drawn through each camera",
            "",
            "Yellow: floor grid every 0.5 m; red/green/blue: world x/y/z (1 m); magenta: 1.8 m "
            "pole at the origin. The grid should lie on the floor in every view.",
            "",
        ]
        for name, image in frames.items():
            cam = rig[name]
            if image.shape[:2] != (cam.height, cam.width):
                lines.append(
                    f"- {name}: frame is {image.shape[1]}x{image.shape[0]}, the calibration says "
                    f"{cam.width}x{cam.height}; no overlay drawn"
                )
                continue
            fname = f"overlay_{stems[name]}.png"
            overlay = draw_world_overlay(cam, image)
            scale = 960 / max(overlay.shape[:2])
            if scale < 1:
                overlay = cv2.resize(
                    overlay, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA
                )
            atomic_write(out / fname, lambda p, img=overlay: _imwrite_png(p, img))
            lines.append(f"![{name}]({fname})")
        lines.append("")
    lines += appendix or []
    md = out / "calibration.md"
    atomic_write_text(md, "\n".join(lines) + "\n")
    return md
