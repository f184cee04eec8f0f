"""The ChArUco calibration board: its spec, printed texture and a path through the volume.

Board frame (OpenCV's): origin at the top-left outer corner of the checker pattern, x along
`squares_x`, y along `squares_y` (down the printed image), z into the board, so the printed
side faces -z. Chessboard corners are `CharucoBoard.getChessboardCorners()`. The printed sheet
has a white margin of `margin` metres around the pattern. A board pose maps board to world:
X_world = R X_board + t.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from synth.world import WORLD_UP

_BOARD_KEYS = ("kind", "squares_x", "squares_y", "square_size", "marker_size", "dictionary")


@dataclass(frozen=True)
class ChArUcoSpec:
    """A ChArUco board, with the same fields as `calibration.board.BoardSpec`."""

    squares_x: int = 5
    squares_y: int = 4
    square_size: float = 0.25
    marker_size: float = 0.18
    dictionary: str = "DICT_4X4_50"
    margin: float = 0.06  # white border of the printed sheet, metres (not part of board.json)

    def __post_init__(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError(f"ChArUco board needs at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_size < self.square_size:
            raise ValueError(f"marker_size {self.marker_size} must be in (0, square_size={self.square_size})")
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary '{self.dictionary}' (expected e.g. DICT_4X4_50)")
        n_markers = (self.squares_x * self.squares_y) // 2
        dict_size = int(self.dictionary.rsplit("_", 1)[-1]) if self.dictionary.rsplit("_", 1)[-1].isdigit() else 1000
        if n_markers > dict_size:
            raise ValueError(f"board needs {n_markers} markers but {self.dictionary} has only {dict_size}")

    def to_dict(self) -> dict:
        """board.json content: exactly the keys of calibration.board.BoardSpec.to_dict()."""
        return {"kind": "charuco", "squares_x": int(self.squares_x), "squares_y": int(self.squares_y),
                "square_size": float(self.square_size), "marker_size": float(self.marker_size),
                "dictionary": self.dictionary}

    @property
    def size(self) -> tuple[float, float]:
        """Pattern width and height in metres (without the margin)."""
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    @cached_property
    def cv_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size, self.marker_size, d)

    @cached_property
    def corners(self) -> np.ndarray:
        """(N, 3) chessboard corners in the board frame (OpenCV order = ChArUco ids)."""
        return np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def texture(self, px_per_square: int = 48) -> BoardTexture:
        """The printed sheet, margin included; pixel edges align with the squares."""
        m = int(round(self.margin / self.square_size * px_per_square))
        w = self.squares_x * px_per_square + 2 * m
        h = self.squares_y * px_per_square + 2 * m
        image = self.cv_board.generateImage((w, h), marginSize=m, borderBits=1)
        return BoardTexture(image=image, px_per_square=px_per_square, margin_px=m,
                            square_size=self.square_size)


@dataclass(frozen=True)
class BoardTexture:
    """Printed board image and its mapping from board metres to image pixels."""

    image: np.ndarray  # (h, w) uint8
    px_per_square: int
    margin_px: int
    square_size: float

    @property
    def margin(self) -> float:
        """Printed white margin in metres (as rendered)."""
        return self.margin_px / self.px_per_square * self.square_size

    def pixel_coords(self, bx: np.ndarray, by: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (pixel centres at integers) of board points in metres."""
        s = self.px_per_square / self.square_size
        return self.margin_px + bx * s - 0.5, self.margin_px + by * s - 0.5


def board_json(spec: ChArUcoSpec) -> dict:
    """board.json dict, cross-checked with calibration.board.BoardSpec when it is installed."""
    d = spec.to_dict()
    try:
        from calibration.board import BoardSpec  # optional until feat/calib is merged
    except ImportError:
        return d
    other = BoardSpec(**d).to_dict()
    if set(other) != set(_BOARD_KEYS) or any(other[k] != d[k] for k in _BOARD_KEYS):
        raise ValueError(f"calibration.board.BoardSpec disagrees with synth's board: {other} vs {d}")
    return other


@dataclass(frozen=True)
class BoardPose:
    """Board-to-world rotation R (3, 3) and translation t (3,)."""

    R: np.ndarray
    t: np.ndarray

    @property
    def front_normal(self) -> np.ndarray:
        """World direction the printed side faces (board -z)."""
        return -self.R[:, 2]

    def to_world(self, points_board: np.ndarray) -> np.ndarray:
        return np.asarray(points_board) @ self.R.T + self.t


def board_path(spec: ChArUcoSpec, n_frames: int, volume_center, volume_radius: float,
               rng: np.random.Generator) -> list[BoardPose]:
    """A smooth hand-held path: the board wanders through the volume at 0.7-1.9 m, turns its
    printed side once around (so every camera of a ring sees it), tilts and rolls."""
    if n_frames < 1:
        raise ValueError(f"board clip needs at least one frame, got {n_frames}")
    c = np.asarray(volume_center, dtype=np.float64)
    tau = np.arange(n_frames) / max(n_frames, 1)
    ph = rng.uniform(0, 2 * np.pi, 4)
    r = 0.55 * volume_radius
    half_diag = 0.5 * np.hypot(*spec.size) + spec.margin
    zc = max(1.25, half_diag + 0.15)
    centre = np.stack([c[0] + r * np.sin(2 * np.pi * 1.0 * tau + ph[0]),
                       c[1] + r * np.sin(2 * np.pi * 2.0 * tau + ph[1]),
                       zc + 0.35 * np.sin(2 * np.pi * 1.5 * tau + ph[2])], -1)
    azimuth = ph[3] + 2 * np.pi * tau * rng.choice([-1.0, 1.0])
    tilt = np.deg2rad(12 + 15 * np.sin(2 * np.pi * 3.0 * tau + ph[0]))  # face up toward high cameras
    roll = np.deg2rad(20 * np.sin(2 * np.pi * 2.5 * tau + ph[1]))
    poses = []
    for i in range(n_frames):
        front = np.array([np.cos(tilt[i]) * np.cos(azimuth[i]), np.cos(tilt[i]) * np.sin(azimuth[i]), np.sin(tilt[i])])
        z = -front  # board z points into the board, away from the viewer
        x = np.cross(z, WORLD_UP)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        x, y = cr * x + sr * y, -sr * x + cr * y
        R = np.stack([x, y, z], -1)
        # Place the pattern centre on the path.
        mid = np.array([spec.size[0] / 2, spec.size[1] / 2, 0.0])
        poses.append(BoardPose(R=R, t=centre[i] - R @ mid))
    return poses


def visible_corners(spec: ChArUcoSpec, pose: BoardPose, camera, radius: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Ids and distorted pixel positions of the chessboard corners a camera sees: printed side
    facing it, in front of it and inside the image (nothing else can hide the board).
    `radius` is the camera's undistorted field radius (`synth.projection.field_radius`)."""
    from synth.projection import project_in_view

    world = pose.to_world(spec.corners)
    ids = np.arange(len(world))
    if np.dot(camera.center - pose.t, pose.front_normal) <= 0:
        return ids[:0], np.zeros((0, 2))
    uv, inside = project_in_view(camera, world, radius)
    return ids[inside], uv[inside]
