"""The ChArUco board, its detection and per-camera intrinsics (OpenCV's aruco module).

Board frame (OpenCV's): the origin at the chessboard's outer corner that is top-left on the
printed image, x to the right along the first row of squares, y down the printed image, z into
the board (away from the printed face). Corner ids run along x first.

Intrinsics: ``cv2.calibrateCamera`` on the object/image points of every view in which enough
corners were found (``CharucoBoard.matchImagePoints``), with k3 fixed at 0 (plumb_bob k1 k2 p1
p2): lenses of lab cameras rarely need k3, and with a dozen views it mostly fits noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

IMAGE_KINDS = ("intrinsics", "board", "hand_eye")  # a camera's image folders under `calibrate rig --images`
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MIN_CORNERS = 6  # corners a view needs to count (a homography needs 4; 6 tolerates one bad one)
MIN_VIEWS = 4  # views an intrinsics fit needs


class CalibrationError(ValueError):
    """A calibration cannot be made or trusted; the message names the camera and the reason."""


@dataclass(frozen=True)
class BoardSpec:
    squares_x: int = 7  # squares along the board's x (its long side, printed left to right)
    squares_y: int = 5  # squares along y
    square_length: float = 0.04  # chessboard square side (m), as printed: measure it
    marker_length: float = 0.03  # ArUco marker side (m)
    dictionary: str = "DICT_5X5_100"  # OpenCV predefined dictionary

    def __post_init__(self):
        if self.squares_x < 2 or self.squares_y < 2:
            raise CalibrationError(f"a board needs at least 2x2 squares, got {self.squares_x}x{self.squares_y}")
        if not 0 < self.square_length < float("inf"):
            raise CalibrationError(f"square length {self.square_length} m must be a positive number of metres")
        if not 0 < self.marker_length < self.square_length:
            raise CalibrationError(
                f"marker length {self.marker_length} m must be positive and below the square length "
                f"{self.square_length} m"
            )
        name = self.dictionary if self.dictionary.startswith("DICT_") else f"DICT_{self.dictionary}"
        if not hasattr(cv2.aruco, name):
            known = sorted(n[5:] for n in dir(cv2.aruco) if n.startswith("DICT_"))
            raise CalibrationError(f"unknown ArUco dictionary {self.dictionary!r}; known: {', '.join(known)}")
        object.__setattr__(self, "dictionary", name)
        markers = (self.squares_x * self.squares_y) // 2
        size = int(name.rsplit("_", 1)[1]) if name.rsplit("_", 1)[1].isdigit() else 10**9
        if markers > size:
            raise CalibrationError(
                f"a {self.squares_x}x{self.squares_y} board needs {markers} markers; {name} has {size}"
            )

    def board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length, self.marker_length, d)

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def image(self, px_per_square: int = 100, margin_px: int | None = None) -> np.ndarray:
        """(H, W) uint8 printable board with a white margin (default half a square)."""
        margin = px_per_square // 2 if margin_px is None else margin_px
        size = (self.squares_x * px_per_square + 2 * margin, self.squares_y * px_per_square + 2 * margin)
        return self.board().generateImage(size, marginSize=margin, borderBits=1)


@dataclass
class Detection:
    """The board's corners found in one image."""

    label: str  # where the image came from (file name)
    ids: np.ndarray  # (N,) corner ids
    object_points: np.ndarray  # (N, 3) board frame (m)
    image_points: np.ndarray  # (N, 2) px


@dataclass
class Intrinsics:
    """One camera's fitted intrinsics."""

    K: np.ndarray  # (3, 3)
    D: np.ndarray  # (5,) k1 k2 p1 p2 k3
    width: int
    height: int
    rms_px: float  # RMS reprojection error over every corner of every used view
    used: list[str] = field(default_factory=list)  # views used
    skipped: dict[str, str] = field(default_factory=dict)  # view -> why it was not used


def read_images(folder: Path, camera: str) -> list[tuple[str, np.ndarray]]:
    """Every image in ``folder`` (sorted by name) as (file name, BGR); unreadable ones are an error."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"camera {camera}: no image folder {folder}")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise CalibrationError(f"camera {camera}: no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    out = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise CalibrationError(f"camera {camera}: cannot read image {p}")
        out.append((p.name, img))
    sizes = {img.shape[:2] for _, img in out}
    if len(sizes) > 1:
        raise CalibrationError(
            f"camera {camera}: images in {folder} differ in size ({', '.join(f'{w}x{h}' for h, w in sorted(sizes))})"
        )
    return out


def detect(board: BoardSpec, image: np.ndarray, label: str = "") -> Detection:
    """The board's ChArUco corners in one image (possibly none)."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    b = board.board()
    detector = cv2.aruco.CharucoDetector(b)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) == 0:
        return Detection(label, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2)))
    obj, img = b.matchImagePoints(corners, ids)
    return Detection(
        label,
        ids.reshape(-1).astype(np.int64),
        np.asarray(obj, np.float64).reshape(-1, 3),
        np.asarray(img, np.float64).reshape(-1, 2),
    )


def usable(board: BoardSpec, det: Detection, min_corners: int = MIN_CORNERS) -> str | None:
    """Why a detection cannot be used, or None."""
    n = len(det.ids)
    if n == 0:
        return "board not found (blurred, too small, badly lit or out of view?)"
    if n < min_corners:
        return f"only {n} of {board.n_corners} corners found (board partly out of view or occluded?)"
    ids = det.ids.reshape(-1, 1).astype(np.int32)
    if board.board().checkCharucoCornersCollinear(ids):
        return f"the {n} corners found lie on one line"
    return None


def describe_skipped(skipped: dict[str, str], limit: int = 3) -> str:
    items = [f"{k}: {v}" for k, v in list(skipped.items())[:limit]]
    more = len(skipped) - limit
    return "; ".join(items) + (f"; and {more} more" if more > 0 else "")


def calibrate_intrinsics(
    camera: str, board: BoardSpec, images: list[tuple[str, np.ndarray]], min_views: int = MIN_VIEWS
) -> Intrinsics:
    """Fit K and distortion from views of the board at varied poses (tilted, across the image)."""
    if not images:
        raise CalibrationError(f"camera {camera}: no images for intrinsics")
    h, w = images[0][1].shape[:2]
    obj, img, used, skipped = [], [], [], {}
    for label, image in images:
        det = detect(board, image, label)
        why = usable(board, det)
        if why:
            skipped[label] = why
            continue
        obj.append(det.object_points.astype(np.float32))
        img.append(det.image_points.astype(np.float32))
        used.append(label)
    if len(used) < min_views:
        raise CalibrationError(
            f"camera {camera}: the board is usable in only {len(used)} of {len(images)} images, "
            f"at least {min_views} needed ({describe_skipped(skipped)})"
        )
    flags = cv2.CALIB_FIX_K3
    rms, K, D, _, _ = cv2.calibrateCamera(obj, img, (w, h), None, None, flags=flags)
    D = np.asarray(D, np.float64).reshape(-1)[:5]
    return Intrinsics(np.asarray(K, np.float64), np.pad(D, (0, 5 - len(D))), w, h, float(rms), used, skipped)
