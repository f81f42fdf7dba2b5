"""Calibration boards (chessboard, ChArUco): detection, intrinsics from many views, the board's pose in one view,
and the camera-to-vehicle transform from a board at a measured place in the vehicle frame. OpenCV.

Board frame (OpenCV's): origin at the board's top-left outer corner, x along its columns (to the right as
printed), y along its rows (down as printed), z into the board; metres.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pallet6d.runtime.geometry import check_K, invert_T, make_T

from .intrinsics import CameraIntrinsics

__all__ = ["BoardSpec", "parse_board", "detect_board", "calibrate_intrinsics", "board_pose",
           "T_vehicle_cam_from_board", "board_image", "render_board"]


@dataclass(frozen=True)
class BoardSpec:
    """A printed board. :ivar kind: "chessboard" or "charuco". :ivar cols, rows: squares across and down.
    :ivar square_m: side of a square. :ivar marker_m: side of a ChArUco marker. :ivar dictionary: ArUco dict name."""

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise ValueError(f"board kind must be chessboard or charuco, got {self.kind!r}")
        if self.cols < 3 or self.rows < 3 or not self.square_m > 0:
            raise ValueError(f"a board needs at least 3x3 squares of positive size, got {self.cols}x{self.rows}, "
                             f"{self.square_m} m")
        if self.kind == "charuco" and not 0 < self.marker_m < self.square_m:
            raise ValueError(f"a ChArUco marker must be smaller than its square, got {self.marker_m} m")
        if self.kind == "charuco" and not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    def charuco(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)


def parse_board(text: str) -> BoardSpec:
    """"chessboard:COLSxROWS:SQUARE_M" or "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]" (squares, metres)."""
    parts = text.split(":")
    try:
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        if parts[0] == "chessboard" and len(parts) == 3:
            return BoardSpec("chessboard", cols, rows, float(parts[2]))
        if parts[0] == "charuco" and len(parts) in (4, 5):
            return BoardSpec("charuco", cols, rows, float(parts[2]), float(parts[3]),
                             *(parts[4:] or ["DICT_5X5_100"]))
    except (IndexError, ValueError):
        pass
    raise ValueError(f"board must be chessboard:COLSxROWS:SQUARE_M or charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] "
                     f"(squares, metres), got {text!r}")


def detect_board(gray: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """Board corners in one image: (n, 3) board-frame points (metres) and (n, 2) pixels; n = 0 when not found.

    :param gray: (H, W) uint8.
    """
    gray = np.asarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be an (H, W) uint8 image, got {gray.shape} {gray.dtype}")
    empty = np.zeros((0, 3)), np.zeros((0, 2))
    if spec.kind == "chessboard":
        pattern = (spec.cols - 1, spec.rows - 1)
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
        if not found:
            return empty
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
        i, j = np.meshgrid(np.arange(1, spec.cols), np.arange(1, spec.rows))
        obj = np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * spec.square_m
        return obj, corners.reshape(-1, 2).astype(np.float64)
    board = spec.charuco()
    cc, ci, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ci is None or len(ci) < 4:
        return empty
    obj, img = board.matchImagePoints(cc, ci)
    return obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)


def calibrate_intrinsics(images: list[np.ndarray], spec: BoardSpec, min_views: int = 5
                         ) -> tuple[CameraIntrinsics, float, int]:
    """Intrinsics from views of a board: (intrinsics, RMS reprojection error in pixels, views used).

    :param images: (H, W) uint8 grey images of one camera. :raises ValueError: fewer than `min_views` views
        show the board.
    """
    if not images:
        raise ValueError("no images")
    h, w = images[0].shape[:2]
    objs, imgs = [], []
    for g in images:
        if g.shape[:2] != (h, w):
            raise ValueError(f"all images must be {w}x{h}, got {g.shape[1]}x{g.shape[0]}")
        o, i = detect_board(g, spec)
        if len(o) >= 6:
            objs.append(o.astype(np.float32))
            imgs.append(i.astype(np.float32))
    if len(objs) < min_views:
        raise ValueError(f"the board was found in {len(objs)} of {len(images)} images, need {min_views}: check "
                         f"the board description ({spec.kind} {spec.cols}x{spec.rows}) and the lighting")
    rms, K, dist, _, _ = cv2.calibrateCamera(objs, imgs, (w, h), None, None)
    return CameraIntrinsics(w, h, K, dist.reshape(-1)[:5]), float(rms), len(objs)


def board_pose(gray: np.ndarray, spec: BoardSpec, K: np.ndarray, dist: np.ndarray | None = None
               ) -> tuple[np.ndarray, float, int]:
    """The board's pose in one image: (T_cam_board (4, 4), RMS reprojection error px, corners used).

    :raises ValueError: the board is not found (fewer than 6 corners).
    """
    if spec.kind != "charuco":
        raise ValueError("a board's pose needs a ChArUco board: a chessboard looks the same turned by 180 degrees")
    K = check_K(K)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    obj, img = detect_board(gray, spec)
    if len(obj) < 6:
        raise ValueError(f"board not found ({len(obj)} corners): is the whole board in view and lit?")
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("solvePnP failed on the board's corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel()), rms, len(obj)


def T_vehicle_cam_from_board(T_vehicle_board: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """(4, 4) camera -> vehicle from the board's measured place in the vehicle frame and its pose in the camera."""
    return np.asarray(T_vehicle_board, dtype=np.float64) @ invert_T(T_cam_board)


def board_image(spec: BoardSpec, px_per_square: int = 100, margin_px: int = 0) -> np.ndarray:
    """The board as a grey uint8 image to print (or to render into a simulated view), `px_per_square` pixels
    per square, with a white margin."""
    size = (spec.cols * px_per_square + 2 * margin_px, spec.rows * px_per_square + 2 * margin_px)
    if spec.kind == "charuco":
        return spec.charuco().generateImage(size, marginSize=margin_px)
    tile = (np.add.outer(np.arange(spec.rows), np.arange(spec.cols)) % 2 == 0)
    img = np.where(np.kron(tile, np.ones((px_per_square, px_per_square))), 0, 255).astype(np.uint8)
    return cv2.copyMakeBorder(img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)


def render_board(spec: BoardSpec, K: np.ndarray, T_cam_board: np.ndarray, image_hw: tuple[int, int],
                 background: int = 128, supersample: int = 4) -> np.ndarray:
    """A grey (H, W) uint8 view of the board at `T_cam_board` through a pinhole camera `K` (antialiased by
    supersampling), for testing the board steps without a camera."""
    h, w = image_hw
    px = 100
    m = spec.square_m / px                                             # board image pixel centres -> metres
    S = np.array([[m, 0, 0.5 * m], [0, m, 0.5 * m], [0, 0, 1]])
    ss = int(supersample)
    A = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1]])   # view pixels -> supersampled
    T = np.asarray(T_cam_board, dtype=np.float64)
    Hm = A @ check_K(K) @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ S
    big = cv2.warpPerspective(board_image(spec, px), Hm, (w * ss, h * ss), flags=cv2.INTER_LINEAR,
                              borderValue=int(background))
    return cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
