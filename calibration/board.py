"""Calibration boards (ChArUco and checkerboard) and their detection in images, videos and folders.

Board coordinates follow OpenCV: origin at the board's top-left outer corner as printed, x along
the rows (to the right), y down the printed page, z into the board, metres. Corner `i` is an inner
chessboard corner; ids run row-major, `i = row * (squares_x - 1) + col`, at
((col + 1) * square_size, (row + 1) * square_size, 0). ChArUco and checkerboard boards share
that numbering, so everything downstream handles them alike.

Subpixel accuracy: ChArUco corners are refined by OpenCV's CharucoDetector (cornerSubPix with a
window that stops short of the nearest marker; we tighten its stopping accuracy to 0.01 px).
Checkerboard corners come from `findChessboardCornersSB`, whose sector-based localisation is
already subpixel.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibration.frames import count_frames, iter_frames, source_image_size

BOARD_KINDS = ("charuco", "checkerboard")
MAX_SQUARE_M = 1.0  # a board of larger squares would be metres across: a size in millimetres
# below this, a size that is not metres may as well be centimetres (a 15 cm square) as
# millimetres; at or above it a square in centimetres would make a board metres wide
CENTIMETRES_BELOW = 40.0


class BoardError(ValueError):
    """A board specification or a detection input is invalid."""


def check_square_metres(square_size: float) -> None:
    """BoardError for a square size that must be millimetres (150 for a 0.15 m board solved a
    rig kilometres wide, labelled metres), or centimetres: 15 for a 15 cm square was told to
    be 0.015 m, and a user who followed that solved a rig ten times too small."""
    if square_size > MAX_SQUARE_M:
        if square_size < CENTIMETRES_BELOW:
            raise BoardError(
                f"board square_size {square_size} m: that looks like centimetres or "
                f"millimetres; give metres ({square_size / 100:g} if it is centimetres, "
                f"{square_size / 1000:g} if millimetres), at most {MAX_SQUARE_M:g} m"
            )
        raise BoardError(
            f"board square_size {square_size} m: that looks like millimetres; give metres "
            f"(e.g. {square_size / 1000:g}), at most {MAX_SQUARE_M:g} m"
        )


@dataclass(frozen=True)
class BoardSpec:
    """A printed calibration board. Sizes in metres.

    `marker_size` and `dictionary` matter for ChArUco only (a checkerboard keeps them for
    round-tripping but ignores them). For a checkerboard, use one odd and one even number of
    squares so that its orientation is unambiguous.
    """

    kind: str
    squares_x: int
    squares_y: int
    square_size: float
    marker_size: float | None = None
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self):
        if self.kind not in BOARD_KINDS:
            raise BoardError(f"board kind '{self.kind}' is unknown, expected one of {BOARD_KINDS}")
        if int(self.squares_x) != self.squares_x or int(self.squares_y) != self.squares_y:
            raise BoardError(
                f"board squares must be integers, got {self.squares_x} x {self.squares_y}"
            )
        if self.squares_x < 3 or self.squares_y < 3:
            raise BoardError(
                f"board needs at least 3 x 3 squares, got {self.squares_x} x {self.squares_y}"
            )
        numbers = (self.square_size, 1.0 if self.marker_size is None else self.marker_size)
        if not all(isinstance(v, (int, float, np.integer, np.floating)) for v in numbers) or any(
            isinstance(v, bool) for v in numbers
        ):  # "0.04" (text) raised numpy's isfinite TypeError
            raise BoardError(
                f"board square_size and marker_size must be numbers (metres), got "
                f"{self.square_size!r} and {self.marker_size!r}"
            )
        if not (np.isfinite(self.square_size) and self.square_size > 0):
            raise BoardError(
                f"board square_size must be a positive length in metres, got {self.square_size}"
            )
        check_square_metres(self.square_size)
        if self.kind == "charuco":
            if self.marker_size is None or not (0 < self.marker_size < self.square_size):
                raise BoardError(
                    f"ChArUco marker_size must be in (0, square_size={self.square_size}), "
                    f"got {self.marker_size}"
                )
            known = (
                isinstance(self.dictionary, str)
                and self.dictionary.startswith("DICT_")
                and isinstance(getattr(cv2.aruco, self.dictionary, None), int)
            )  # hasattr took any cv2.aruco name (CORNER_REFINE_SUBPIX: DICT_4X4_100's number)
            if not known:
                raise BoardError(
                    f"ArUco dictionary '{self.dictionary}' is unknown to OpenCV "
                    "(expected a name such as 'DICT_5X5_100')"
                )
            n_markers = (self.squares_x * self.squares_y) // 2
            dict_size = len(
                cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList
            )
            if n_markers > dict_size:
                raise BoardError(
                    f"board needs {n_markers} markers but {self.dictionary} has only {dict_size}"
                )
        elif (self.squares_x + self.squares_y) % 2 == 0:
            raise BoardError(
                f"checkerboard {self.squares_x} x {self.squares_y}: use one odd and one even "
                "number of squares, otherwise its orientation (and so which corner is which) is "
                "ambiguous"
            )

    # -- serialisation --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "squares_x": int(self.squares_x),
            "squares_y": int(self.squares_y),
            "square_size": float(self.square_size),
            "marker_size": None if self.marker_size is None else float(self.marker_size),
            "dictionary": self.dictionary,
        }

    @classmethod
    def from_dict(cls, data: dict) -> BoardSpec:
        expected = {"kind", "squares_x", "squares_y", "square_size", "marker_size", "dictionary"}
        unknown = set(data) - expected
        missing = {"kind", "squares_x", "squares_y", "square_size"} - set(data)
        if unknown or missing:
            raise BoardError(
                f"board spec keys: unknown {sorted(unknown)}, missing {sorted(missing)}; "
                f"expected {sorted(expected)}"
            )
        return cls(
            kind=data["kind"],
            squares_x=int(data["squares_x"]),
            squares_y=int(data["squares_y"]),
            square_size=float(data["square_size"]),
            marker_size=None if data.get("marker_size") is None else float(data["marker_size"]),
            dictionary=data.get("dictionary", "DICT_5X5_100"),
        )

    # -- geometry -------------------------------------------------------------------------------
    @property
    def inner_corners(self) -> tuple[int, int]:
        """Inner corner grid (columns, rows)."""
        return self.squares_x - 1, self.squares_y - 1

    @property
    def n_corners(self) -> int:
        cols, rows = self.inner_corners
        return cols * rows

    @property
    def size_m(self) -> tuple[float, float]:
        """Board extent (width, height) in metres."""
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    def object_points(self) -> np.ndarray:
        """(n_corners, 3) corner positions in board coordinates, indexed by corner id."""
        cols, rows = self.inner_corners
        c, r = np.meshgrid(np.arange(cols), np.arange(rows))
        pts = np.stack(
            [
                (c.ravel() + 1) * self.square_size,
                (r.ravel() + 1) * self.square_size,
                np.zeros(cols * rows),
            ],
            axis=1,
        )
        return pts.astype(np.float64)

    def create_cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board (ChArUco only; checkerboards have no OpenCV board object)."""
        if self.kind != "charuco":
            raise BoardError(
                "create_cv_board() is for ChArUco boards; a checkerboard is detected "
                "with cv2.findChessboardCornersSB and needs no board object"
            )
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_size, self.marker_size, dictionary
        )

    def render_image(self, px_per_square: int = 100, margin_px: int = 0) -> np.ndarray:
        """The printable board as a uint8 grayscale image (square (0, 0) is black).

        Texel (i, j) of the board area covers board coordinates
        [i, i + 1] * s / px_per_square x [j, j + 1] * s / px_per_square, s = square_size.
        """
        px_per_square = int(px_per_square)
        if px_per_square < 8:
            raise BoardError(f"px_per_square must be >= 8, got {px_per_square}")
        w, h = self.squares_x * px_per_square, self.squares_y * px_per_square
        if self.kind == "charuco":
            img = self.create_cv_board().generateImage((w, h), marginSize=0, borderBits=1)
        else:
            yy, xx = np.mgrid[0:h, 0:w] // px_per_square
            img = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
        if margin_px:
            img = cv2.copyMakeBorder(
                img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255
            )
        return img


@dataclass(frozen=True)
class FrameDetection:
    """Board corners found in one frame of one camera."""

    frame: int  # frame index in the source (video frame number or position in the image folder)
    ids: np.ndarray  # (M,) int corner ids, see BoardSpec.object_points
    corners: np.ndarray  # (M, 2) float64 pixel positions (OpenCV pixel convention)
    sharpness: float = float("nan")  # blur measure, larger is sharper (`_sharpness`)

    def __post_init__(self):
        ids = np.asarray(self.ids, dtype=np.int64).ravel()
        corners = np.asarray(self.corners, dtype=np.float64).reshape(-1, 2)
        if len(ids) != len(corners):
            raise BoardError(f"frame {self.frame}: {len(ids)} ids but {len(corners)} corners")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners", corners)


@dataclass
class CameraDetections:
    """All board detections of one camera, with how many frames were searched."""

    camera: str
    image_size: tuple[int, int]  # (width, height)
    frames_searched: int
    detections: list[FrameDetection] = field(default_factory=list)


class BoardDetector:
    """Finds board corners in grayscale or colour images. Build once per board, reuse per frame."""

    def __init__(self, board: BoardSpec, min_corners: int = 6):
        self.board = board
        self.min_corners = max(int(min_corners), 4)
        if board.n_corners < self.min_corners:  # a 3 x 3 board's 4 corners were never enough
            raise BoardError(
                f"board {board.squares_x} x {board.squares_y} has {board.n_corners} inner corners,"
                f" fewer than the {self.min_corners} a detection needs: use a board with more "
                "squares (or lower min_corners)"
            )
        if board.kind == "charuco":
            params = cv2.aruco.DetectorParameters()
            # Finer stopping accuracy for the corner refinement than OpenCV's 0.1 px default.
            params.cornerRefinementMinAccuracy = 0.01
            params.cornerRefinementMaxIterations = 50
            charuco_params = cv2.aruco.CharucoParameters()
            charuco_params.tryRefineMarkers = True  # recover markers missed in blurred frames
            self._detector = cv2.aruco.CharucoDetector(
                board.create_cv_board(), charuco_params, params
            )
        else:
            self._detector = None

    def detect(self, image: np.ndarray, frame: int = 0) -> FrameDetection | None:
        """Corners in one image, or None when fewer than `min_corners` (or a degenerate set)
        show."""
        image = np.asarray(image)
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[..., 0]
        if (
            image.dtype != np.uint8
            or image.ndim not in (2, 3)
            or (image.ndim == 3 and image.shape[2] not in (3, 4))
        ):  # raw OpenCV assertions ("_in.type() == CV_8UC1") before
            raise BoardError(
                f"board detection needs an 8-bit grey, BGR or BGRA image, got dtype "
                f"{image.dtype} and shape {image.shape}"
            )
        if image.ndim == 2:
            gray = image
        else:
            code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            gray = cv2.cvtColor(image, code)
        if self.board.kind == "charuco":
            corners, ids, _, _ = self._detector.detectBoard(gray)
            if ids is None or len(ids) < self.min_corners:
                return None
            ids, corners = ids.ravel(), corners.reshape(-1, 2)
        else:
            flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            found, corners = cv2.findChessboardCornersSB(
                gray, self.board.inner_corners, flags=flags
            )
            if not found:
                return None
            corners = _orient_checkerboard(gray, corners.reshape(-1, 2), self.board)
            if corners is None:
                return None
            ids = np.arange(len(corners))
        obj = self.board.object_points()[ids, :2]
        if not spans_plane(obj):
            return None  # collinear corners constrain no pose
        return FrameDetection(
            frame=frame,
            ids=ids,
            corners=corners.astype(np.float64),
            sharpness=_sharpness(gray, corners),
        )


def _orient_checkerboard(
    gray: np.ndarray, corners: np.ndarray, board: BoardSpec
) -> np.ndarray | None:
    """Reorder findChessboardCornersSB's corners to our id order (None: not decidable).

    OpenCV may start the grid at any outer corner. A printed board seen from the front keeps its
    handedness, so a mirrored order is undone first; then the squares' colours settle the
    remaining 180-degree ambiguity: square (i, j) is black where i + j is even, and a half turn
    swaps the colours of every square (one side has an odd and the other an even number of
    squares). Only the inner squares are read, the ones inside the detected corner grid: an
    outer square may be cut off by the image's edge while OpenCV still finds every inner
    corner (a board pushed into the image's corner, as calibration asks for); the order was
    then left as OpenCV gave it, every id turned by half when OpenCV's grid started at the far
    end.
    """
    cols, rows = board.inner_corners
    grid = corners.reshape(rows, cols, 2)
    obj = board.object_points()[:, :2]
    H, _ = cv2.findHomography(obj, grid.reshape(-1, 2))
    if H is not None:
        # Orientation of the board->image map at the board centre: negative means mirrored.
        centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2])
        if _local_jacobian_det(H, centre) < 0:
            grid = grid[:, ::-1]
            H, _ = cv2.findHomography(obj, grid.reshape(-1, 2))
    if H is None:
        return None
    i, j = np.meshgrid(np.arange(1, board.squares_x - 1), np.arange(1, board.squares_y - 1))
    i, j = i.ravel(), j.ravel()
    centres = (np.c_[i, j] + 0.5) * board.square_size
    px = cv2.perspectiveTransform(centres.reshape(-1, 1, 2), H).reshape(-1, 2)
    values = np.array([np.nan if (v := _sample(gray, p)) is None else v for p in px])
    black, white = values[(i + j) % 2 == 0], values[(i + j) % 2 == 1]
    black, white = black[np.isfinite(black)], white[np.isfinite(white)]
    if not len(black) or not len(white) or black.mean() == white.mean():
        return None
    if black.mean() > white.mean():
        grid = grid[::-1, ::-1]
    return np.ascontiguousarray(grid.reshape(-1, 2))


def _local_jacobian_det(H: np.ndarray, xy: np.ndarray) -> float:
    eps = 1e-3
    pts = np.array([xy, xy + [eps, 0], xy + [0, eps]]).reshape(-1, 1, 2)
    p = cv2.perspectiveTransform(pts, H).reshape(-1, 2)
    return float(np.linalg.det(np.stack([p[1] - p[0], p[2] - p[0]])))


def _sample(gray: np.ndarray, xy: np.ndarray) -> float | None:
    x, y = int(round(xy[0])), int(round(xy[1]))
    h, w = gray.shape[:2]
    if not (1 <= x < w - 1 and 1 <= y < h - 1):
        return None
    return float(gray[y - 1 : y + 2, x - 1 : x + 2].mean())


def spans_plane(points_2d: np.ndarray, min_ratio: float = 0.05) -> bool:
    """True when 2D points are not (nearly) collinear: the smaller principal extent is at least
    `min_ratio` of the larger one."""
    if len(points_2d) < 4:
        return False
    s = np.linalg.svd(points_2d - points_2d.mean(axis=0), compute_uv=False)
    return bool(s[0] > 0 and s[1] / s[0] >= min_ratio)


def _sharpness(gray: np.ndarray, corners: np.ndarray) -> float:
    """A blur measure that does not depend on how large the board is in the image: the variance
    of the Laplacian inside the corners' bounding box, times the corners' spacing in pixels
    (median distance to the nearest corner). The Laplacian answers at the squares' edges only,
    and their share of the box falls as the squares grow (as 1 / spacing), so the variance
    alone read a sharp board 1 m away as 7x blurrier than the same board at 5 m and dropped it
    (`drop_blurred`): the close views that pin the focal length and the distortion."""
    x0, y0 = np.floor(corners.min(axis=0)).astype(int)
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 1
    h, w = gray.shape[:2]
    roi = gray[max(y0, 0) : min(y1, h), max(x0, 0) : min(x1, w)]
    if roi.size < 9 or len(corners) < 2:
        return float("nan")
    d = np.linalg.norm(corners[:, None] - corners[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(cv2.Laplacian(roi, cv2.CV_64F).var() * np.median(d.min(axis=1)))


def detect_in_source(
    source: str | Path,
    board: BoardSpec,
    *,
    camera: str | None = None,
    frame_step: int = 1,
    max_frames: int | None = None,
    min_corners: int = 6,
    min_sharpness_ratio: float = 0.2,
    progress: Callable[[str, int, int], None] | None = None,
) -> CameraDetections:
    """Detect the board in every `frame_step`-th frame of a video file or an image folder.

    Blurred frames: a detection whose sharpness is below `min_sharpness_ratio` times the camera's
    median sharpness is dropped (motion blur moves corners). Partial views are kept as long as at
    least `min_corners` non-collinear corners were found. `progress(camera, done, total)` is
    called now and then.
    """
    source = Path(source)
    name = camera or source.stem
    total = count_frames(source)
    n_search = len(range(0, total, max(int(frame_step), 1)))
    if max_frames is not None:
        n_search = min(n_search, int(max_frames))
    detector = BoardDetector(board, min_corners=min_corners)
    found: list[FrameDetection] = []
    searched = 0
    for index, image in iter_frames(source, frame_step=frame_step, max_frames=max_frames):
        searched += 1
        det = detector.detect(image, frame=index)
        if det is not None:
            found.append(det)
        if progress is not None and (searched % 10 == 0 or searched == n_search):
            progress(name, searched, n_search)
    found = drop_blurred(found, min_sharpness_ratio)
    return CameraDetections(
        camera=name,
        image_size=source_image_size(source),
        frames_searched=searched,
        detections=found,
    )


def drop_blurred(detections: Iterable[FrameDetection], min_ratio: float) -> list[FrameDetection]:
    """Detections whose sharpness is at least `min_ratio` x the median sharpness."""
    detections = list(detections)
    sharp = np.array([d.sharpness for d in detections], dtype=np.float64)
    if min_ratio <= 0 or not np.any(np.isfinite(sharp)):
        return detections
    floor = min_ratio * np.nanmedian(sharp)
    return [d for d, s in zip(detections, sharp, strict=True) if not np.isfinite(s) or s >= floor]


def detect_in_sources(
    sources: dict[str, str | Path],
    board: BoardSpec,
    *,
    frame_step: int = 1,
    max_frames: int | None = None,
    min_corners: int = 6,
    min_sharpness_ratio: float = 0.2,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, CameraDetections]:
    """`detect_in_source` for each camera (name -> video file or image folder)."""
    if not sources:
        raise BoardError("no camera sources given")
    return {
        name: detect_in_source(
            path,
            board,
            camera=name,
            frame_step=frame_step,
            max_frames=max_frames,
            min_corners=min_corners,
            min_sharpness_ratio=min_sharpness_ratio,
            progress=progress,
        )
        for name, path in sources.items()
    }
