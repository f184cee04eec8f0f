"""Synthetic board footage with known truth, for tests, benchmarks and demos.

A ring of cameras looks into a capture volume; a board first lies flat on the floor and then
moves through the volume facing one way or another, so each pose is seen by a few cameras only.
Images are rendered exactly: every (supersampled) pixel's ray is undistorted with the camera's
true model, intersected with the board plane and looked up in the printed board image, then
blurred and given pixel noise. Detections can also be made directly from the truth (projected
corners plus Gaussian noise) when image rendering is not the point.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from calibration.board import BoardSpec, FrameDetection
from calibration.camera import Camera, Rig, look_at_rotation

# Board z points into the board; lying face-up on the floor it points down: board -> world axes.
FLOOR_BOARD_AXES = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class BoardScene:
    """Truth for synthetic board footage: the rig, the board and its pose in every frame."""

    rig: Rig
    board: BoardSpec
    world_from_board: np.ndarray  # (F, 4, 4)
    floor_frame: int = 0  # the frame in which the board lies flat on the floor


def ring_rig(
    n_cameras: int = 8,
    radius: float = 3.0,
    height: float = 2.2,
    look_at=(0.0, 0.0, 0.9),
    image_size: tuple[int, int] = (800, 600),
    focal_px: float = 700.0,
    dist=(-0.12, 0.06, 0.0005, -0.0004, 0.0),
    seed: int | None = 0,
) -> Rig:
    """Cameras evenly spaced on a circle, aimed at `look_at`. With a seed, each camera's focal
    length (+-4%), principal point (+-2% of the size), distortion and aim vary a little."""
    rng = np.random.default_rng(seed)
    w, h = image_size
    cams = []
    for i in range(n_cameras):
        a = 2 * np.pi * i / n_cameras
        pos = np.array([radius * np.cos(a), radius * np.sin(a), height])
        target = np.asarray(look_at, dtype=np.float64)
        f, cx, cy, d = focal_px, (w - 1) / 2, (h - 1) / 2, np.array(dist, dtype=np.float64)
        if seed is not None:
            f *= 1 + rng.uniform(-0.04, 0.04)
            cx += rng.uniform(-0.02, 0.02) * w
            cy += rng.uniform(-0.02, 0.02) * h
            d = d * rng.uniform(0.8, 1.2, size=d.shape)
            pos = pos + rng.uniform(-0.1, 0.1, 3)
            target = target + rng.uniform(-0.2, 0.2, 3)
        R = look_at_rotation(pos, target)
        K = [
            [f * (1 + (rng.uniform(-0.003, 0.003) if seed is not None else 0)), 0, cx],
            [0, f, cy],
            [0, 0, 1],
        ]
        cams.append(Camera.create(f"cam{i:02d}", K, d, R, -R @ pos, w, h, {"source": "synthetic"}))
    return Rig(tuple(cams), up=(0.0, 0.0, 1.0))


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rot(axis, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)[0]


def board_poses(
    board: BoardSpec,
    n_frames: int,
    *,
    floor_xy=(0.0, 0.0),
    volume_radius: float = 1.5,
    heights=(0.4, 2.0),
    seed: int = 0,
) -> np.ndarray:
    """(n_frames, 4, 4) world_from_board poses: frame 0 flat on the floor (face up, centred on
    `floor_xy`), the rest at random places in a cylinder, facing a random horizontal direction,
    tilted up to 40 degrees and turned in-plane up to 30 degrees."""
    rng = np.random.default_rng(seed)
    w, h = board.size_m
    centre_b = np.array([w / 2, h / 2, 0.0])
    poses = [
        _pose(
            FLOOR_BOARD_AXES,
            np.array([floor_xy[0], floor_xy[1], 0.0]) - FLOOR_BOARD_AXES @ centre_b,
        )
    ]
    for _ in range(n_frames - 1):
        r, a = volume_radius * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        centre = np.array([r * np.cos(a), r * np.sin(a), rng.uniform(*heights)])
        facing = rng.uniform(0, 2 * np.pi)  # azimuth of the printed face's normal
        n = np.array([np.cos(facing), np.sin(facing), 0.0])  # front normal = -board z
        side = np.cross([0.0, 0.0, 1.0], n)  # board x, horizontal
        Rb = np.stack([side, np.array([0.0, 0.0, -1.0]), -n], axis=1)  # board y points down
        Rb = _rot(side, rng.uniform(-0.7, 0.35)) @ Rb  # tilt the face up (negative) or down
        Rb = Rb @ _rot([0, 0, 1], rng.uniform(-0.5, 0.5))  # in-plane turn
        poses.append(_pose(Rb, centre - Rb @ centre_b))
    return np.stack(poses)


def make_scene(
    n_cameras: int = 8,
    n_frames: int = 60,
    board: BoardSpec | None = None,
    seed: int = 0,
    **rig_kwargs,
) -> BoardScene:
    """A ring rig and a board trajectory. The floor pose sits off-centre, toward camera 0, so
    that camera 0 does not see it: then no board pose is seen by every camera."""
    board = board or BoardSpec("charuco", 7, 5, 0.15, 0.11, "DICT_4X4_50")
    rig = ring_rig(n_cameras, seed=seed, **rig_kwargs)
    radius = rig_kwargs.get("radius", 3.0)
    poses = board_poses(board, n_frames, floor_xy=(0.45 * radius, 0.0), seed=seed + 1)
    return BoardScene(rig, board, poses, floor_frame=0)


def visible_corners(
    camera: Camera,
    board: BoardSpec,
    world_from_board: np.ndarray,
    *,
    margin_px: float = 4.0,
    max_incidence_deg: float = 75.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(ids, pixels) of the corners a camera sees: printed face toward it at an incidence below
    `max_incidence_deg`, in front of it and inside the image by `margin_px`."""
    Rb, tb = world_from_board[:3, :3], world_from_board[:3, 3]
    front = -Rb[:, 2]
    to_cam = camera.center - (tb + Rb @ (np.array([*board.size_m, 0.0]) / 2))
    cos_inc = float(front @ to_cam / np.linalg.norm(to_cam))
    if cos_inc < np.cos(np.radians(max_incidence_deg)):
        return np.zeros(0, int), np.zeros((0, 2))
    pts = board.object_points() @ Rb.T + tb
    depth = camera.to_camera(pts)[:, 2]
    uv = camera.project(pts)
    ok = (
        (depth > 0.05)
        & (uv[:, 0] >= margin_px)
        & (uv[:, 1] >= margin_px)
        & (uv[:, 0] <= camera.width - 1 - margin_px)
        & (uv[:, 1] <= camera.height - 1 - margin_px)
    )
    return np.flatnonzero(ok), uv[ok]


def synthetic_detections(
    scene: BoardScene, noise_px: float = 0.3, min_corners: int = 6, seed: int = 0
) -> dict[str, list[FrameDetection]]:
    """Per camera, per frame: the truly visible corners with Gaussian pixel noise added."""
    rng = np.random.default_rng(seed)
    out: dict[str, list[FrameDetection]] = {c.name: [] for c in scene.rig}
    for f, T in enumerate(scene.world_from_board):
        for cam in scene.rig:
            ids, uv = visible_corners(cam, scene.board, T)
            if len(ids) >= min_corners:
                out[cam.name].append(FrameDetection(f, ids, uv + rng.normal(0, noise_px, uv.shape)))
    return out


def _undistorted_rays(camera: Camera, supersample: int, step: int = 8) -> np.ndarray:
    """(H*ss, W*ss, 3) normalised rays [x, y, 1] through the centres of supersampled pixels.

    The undistortion is exact (iterative) on a grid every `step` supersampled pixels and
    interpolated by a bicubic spline in between: it is smooth, so this is accurate to ~1e-5 px and
    much faster than undistorting every pixel.
    """
    W, H = camera.width * supersample, camera.height * supersample
    gx = np.arange(0, W + step, step)  # the coarse grid extends past the last pixel
    gy = np.arange(0, H + step, step)
    gu, gv = np.meshgrid((gx + 0.5) / supersample - 0.5, (gy + 0.5) / supersample - 0.5)
    xy = camera.undistort_points(np.stack([gu.ravel(), gv.ravel()], axis=1)).reshape(
        len(gy), len(gx), 2
    )
    rays = np.ones((H, W, 3))
    for k in range(2):
        spline = RectBivariateSpline(gy, gx, xy[..., k], kx=3, ky=3)
        rays[..., k] = spline(np.arange(H), np.arange(W), grid=True)
    return rays


class BoardRenderer:
    """Renders the board into one camera exactly (true projection and distortion)."""

    def __init__(
        self,
        camera: Camera,
        board: BoardSpec,
        px_per_square: int = 120,
        supersample: int = 2,
        background: int = 110,
    ):
        self.camera, self.board, self.ss, self.background = (
            camera,
            board,
            int(supersample),
            background,
        )
        self.texture = board.render_image(px_per_square).astype(np.float32)
        self.metres_per_texel = board.square_size / px_per_square
        self.rays = _undistorted_rays(camera, self.ss)
        w, h = board.size_m
        s = np.linspace(0, 1, 33)
        z = np.zeros_like(s)
        self.outline = np.concatenate(
            [
                np.stack([s * w, z, z], 1),
                np.stack([s * w, z + h, z], 1),
                np.stack([z, s * h, z], 1),
                np.stack([z + w, s * h, z], 1),
            ]
        )

    def _roi(self, world_from_board: np.ndarray) -> tuple[int, int, int, int]:
        """Pixel box (x0, y0, x1, y1) holding the board's image; the whole image if unsure."""
        cam = self.camera
        pts = self.outline @ world_from_board[:3, :3].T + world_from_board[:3, 3]
        if np.any(cam.to_camera(pts)[:, 2] <= 1e-3):
            return 0, 0, cam.width, cam.height
        uv = cam.project(pts)
        x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 3
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 4
        return max(x0, 0), max(y0, 0), min(max(x1, 0), cam.width), min(max(y1, 0), cam.height)

    def render(
        self,
        world_from_board: np.ndarray,
        blur_sigma: float = 0.0,
        noise_std: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """uint8 grayscale image of the board at `world_from_board`."""
        cam, ss = self.camera, self.ss
        img = np.full((cam.height, cam.width), float(self.background), dtype=np.float32)
        x0, y0, x1, y1 = self._roi(world_from_board)
        if x1 > x0 and y1 > y0:
            cam_from_board = cam.world_to_cam @ world_from_board
            Rcb, tcb = cam_from_board[:3, :3], cam_from_board[:3, 3]
            # Board plane (z = 0) to normalised image: [x_n, y_n, 1] ~ [r1 r2 t] [x, y, 1].
            Hinv = np.linalg.inv(np.column_stack([Rcb[:, 0], Rcb[:, 1], tcb]))
            rays = self.rays[y0 * ss : y1 * ss, x0 * ss : x1 * ss]
            b = rays @ Hinv.T  # = [x, y, 1] / depth
            hit = b[..., 2] > 0  # the ray meets the plane in front of the camera
            with np.errstate(divide="ignore", invalid="ignore"):
                mx = np.where(hit, b[..., 0] / b[..., 2] / self.metres_per_texel - 0.5, -1e6)
                my = np.where(hit, b[..., 1] / b[..., 2] / self.metres_per_texel - 0.5, -1e6)
            front = float(Rcb[:, 2] @ tcb) > 0  # camera on the printed side (board -z)
            tex = self.texture if front else np.full_like(self.texture, 200.0)  # back of the board
            patch = cv2.remap(
                tex,
                mx.astype(np.float32),
                my.astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float(self.background),
            )
            if ss > 1:
                patch = cv2.resize(patch, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
            img[y0:y1, x0:x1] = patch
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        if noise_std > 0:
            img = img + (rng or np.random.default_rng()).normal(0, noise_std, img.shape).astype(
                np.float32
            )
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_scene(
    scene: BoardScene,
    out_dir: str | Path,
    *,
    as_video: bool = False,
    blur_sigma: float = 0.7,
    noise_std: float = 2.0,
    px_per_square: int = 120,
    supersample: int = 2,
    seed: int = 0,
) -> dict[str, Path]:
    """Write every camera's footage (PNG folder, or a lossless FFV1 .mkv video) and return the
    camera name -> source path mapping `calibrate_from_board` takes."""
    rng = np.random.default_rng(seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sources: dict[str, Path] = {}
    for cam in scene.rig:
        renderer = BoardRenderer(cam, scene.board, px_per_square, supersample)
        frames = (renderer.render(T, blur_sigma, noise_std, rng) for T in scene.world_from_board)
        if as_video:
            path = out_dir / f"{cam.name}.mkv"
            writer = cv2.VideoWriter(
                str(path),
                cv2.VideoWriter_fourcc(*"FFV1"),
                30.0,
                (cam.width, cam.height),
                isColor=False,
            )
            if not writer.isOpened():
                raise RuntimeError(f"OpenCV cannot write FFV1 video to '{path}'")
            for img in frames:
                writer.write(img)
            writer.release()
        else:
            path = out_dir / cam.name
            path.mkdir(exist_ok=True)
            for f, img in enumerate(frames):
                cv2.imwrite(str(path / f"{f:05d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        sources[cam.name] = path
    return sources
