"""Camera calibration from views of a ChArUco or chessboard target (pure logic, no ROS).

Intrinsics and lens distortion come from several views of the target (`cv2.calibrateCamera`,
OpenCV's pinhole + radial/tangential model). The sample plane comes from one view of the
target lying on it: the target's pose in that view gives the homography from undistorted
camera pixels to a square-on pixel grid of the plane, the grid `metarig track` works in.

Board frame (OpenCV's object points): X along the board's columns of squares, Y along its
rows, both in metres, as the board is printed (Y runs down the printed picture). The sample
frame written to the calibration is the board seen square-on from the camera's side, with
x = X - X0 along the bottom edge to the right and y = Y0 - Y up, its origin at the board's
bottom-left corner (X0, Y0): ChArUco, the outer corner of its squares (0, rows * square);
chessboard, its bottom-left inner corner (0, (inner rows - 1) * square). A chessboard's top
left is the end whose corner square is black: with an even number of inner corners one way
and an odd one the other, the opposite corner square is white and the orientation is
defined; otherwise both are black and the board may be taken turned by 180 degrees (the
sample frame then turns with it).
"""

import math
import re
from dataclasses import dataclass

import cv2
import numpy as np


class CameraCalibrationError(ValueError):
    """The target, the images or the fit cannot give a usable calibration (message says why)."""


_BOARD_KEYS = {"charuco": ("squares", "square", "marker", "dict"),
               "chessboard": ("inner", "square")}
_SPEC_HELP = ("board spec: 'charuco:squares=COLSxROWS,square=M,marker=M,dict=DICT_5X5_100' or "
              "'chessboard:inner=COLSxROWS,square=M' (lengths in metres)")


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """A calibration target.

    Attributes:
        kind: "charuco" or "chessboard".
        cols, rows: ChArUco: squares across and down; chessboard: inner corners across, down.
        square_m: side of one square, m.
        marker_m: side of an ArUco marker, m (ChArUco only, else 0).
        dictionary: ArUco dictionary name, e.g. "DICT_5X5_100" (ChArUco only, else "").
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = ""

    def __str__(self) -> str:
        if self.kind == "charuco":
            return (f"charuco:squares={self.cols}x{self.rows},square={self.square_m:g},"
                    f"marker={self.marker_m:g},dict={self.dictionary}")
        return f"chessboard:inner={self.cols}x{self.rows},square={self.square_m:g}"

    @property
    def origin_m(self) -> tuple[float, float]:
        """Board-frame (X0, Y0) of the sample origin, the board's bottom-left corner, m."""
        rows = self.rows if self.kind == "charuco" else self.rows - 1
        return 0.0, rows * self.square_m

    @property
    def extent_m(self) -> tuple[float, float]:
        """Width and height of the patterned area (ChArUco squares; chessboard inner corners), m."""
        if self.kind == "charuco":
            return self.cols * self.square_m, self.rows * self.square_m
        return (self.cols - 1) * self.square_m, (self.rows - 1) * self.square_m

    def cv_board(self):
        """The `cv2.aruco.CharucoBoard` (ChArUco only)."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)

    def corner_points(self) -> np.ndarray:
        """Board-frame (X, Y) of every corner id [n_corners, 2], m (row-major, from top left)."""
        if self.kind == "charuco":
            return np.asarray(self.cv_board().getChessboardCorners(), np.float64)[:, :2]
        jj, ii = np.mgrid[0:self.rows, 0:self.cols]
        return np.column_stack([ii.ravel(), jj.ravel()]).astype(np.float64) * self.square_m


def _grid(value: str, key: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", value)
    if not m:
        raise CameraCalibrationError(f"board {key}={value!r}: expected COLSxROWS, e.g. 11x8")
    return int(m.group(1)), int(m.group(2))


def _length(value: str, key: str) -> float:
    try:
        v = float(value)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise CameraCalibrationError(f"board {key}={value!r}: expected a positive length in m")
    return v


def parse_board(spec: str) -> BoardSpec:
    """Parse a board spec string (see `_SPEC_HELP`); raises `CameraCalibrationError`."""
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    if kind not in _BOARD_KEYS:
        raise CameraCalibrationError(f"unknown board kind {kind!r}; {_SPEC_HELP}")
    fields: dict[str, str] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip().lower()
        if not eq or key not in _BOARD_KEYS[kind]:
            raise CameraCalibrationError(f"board {kind}: unknown field {item!r}; {_SPEC_HELP}")
        fields[key] = value.strip()
    missing = [k for k in _BOARD_KEYS[kind] if k not in fields]
    if missing:
        raise CameraCalibrationError(f"board {kind}: missing {', '.join(missing)}; {_SPEC_HELP}")
    square = _length(fields["square"], "square")
    if kind == "chessboard":
        cols, rows = _grid(fields["inner"], "inner")
        if min(cols, rows) < 2:
            raise CameraCalibrationError("board inner corners must be at least 2x2")
        return BoardSpec("chessboard", cols, rows, square)
    cols, rows = _grid(fields["squares"], "squares")
    if min(cols, rows) < 3:
        raise CameraCalibrationError("board squares must be at least 3x3")
    marker = _length(fields["marker"], "marker")
    if marker >= square:
        raise CameraCalibrationError(f"board marker {marker:g} m must be smaller than its "
                                     f"square {square:g} m")
    name = fields["dict"].upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise CameraCalibrationError(f"board dict={fields['dict']!r}: not an ArUco dictionary "
                                     "(e.g. DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    board = BoardSpec("charuco", cols, rows, square, marker, name)
    n_markers = (cols * rows) // 2
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if n_markers > size:
        raise CameraCalibrationError(f"board needs {n_markers} markers but {name} has {size}")
    return board


@dataclass(frozen=True, slots=True)
class Detection:
    """Target corners found in one image.

    Attributes:
        ids: [k] corner ids (index into `BoardSpec.corner_points`).
        image_px: [k, 2] (col, row) raw pixel positions, sub-pixel.
        board_m: [k, 2] their (X, Y) in the board frame, m.
    """

    ids: np.ndarray
    image_px: np.ndarray
    board_m: np.ndarray

    @property
    def object_points(self) -> np.ndarray:
        """[k, 1, 3] float32 (X, Y, 0) for OpenCV."""
        k = len(self.ids)
        return np.column_stack([self.board_m, np.zeros(k)]).astype(np.float32).reshape(k, 1, 3)

    @property
    def image_points(self) -> np.ndarray:
        """[k, 1, 2] float32 for OpenCV."""
        return self.image_px.astype(np.float32).reshape(-1, 1, 2)


def detect(board: BoardSpec, gray: np.ndarray, min_corners: int = 8) -> Detection | None:
    """Find the target's corners in a grey uint8 image; None with fewer than `min_corners`."""
    corners_m = board.corner_points()
    if board.kind == "charuco":
        det = cv2.aruco.CharucoDetector(board.cv_board())
        corners, ids, _, _ = det.detectBoard(gray)
        if ids is None or len(ids) < min_corners:
            return None
        ids = ids.ravel().astype(np.int64)
        px = _refine_charuco(gray, corners.reshape(-1, 2).astype(np.float32),
                             board.marker_m / board.square_m)
    else:
        ok, corners = cv2.findChessboardCornersSB(
            gray, (board.cols, board.rows), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not ok or corners is None:
            return None
        px = _orient_chessboard(gray, corners.reshape(-1, 2).astype(np.float64), board)
        ids = np.arange(len(px))
    return Detection(ids=ids, image_px=px, board_m=corners_m[ids])


def _refine_charuco(gray: np.ndarray, px: np.ndarray, marker_share: float) -> np.ndarray:
    """Corners refined by `cv2.cornerSubPix` in a window that stays inside the white margin
    around the markers (the detector's own window is fixed in pixels and may reach them)."""
    d = np.sqrt(((px[:, None, :] - px[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    square_px = float(np.median(d.min(1)))  # the nearest corner is one square away
    half = int(np.clip(np.floor(0.8 * square_px * (1.0 - marker_share) / 2), 2, 15))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    out = cv2.cornerSubPix(gray, px.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), crit)
    return out.reshape(-1, 2).astype(np.float64)


def _orient_chessboard(gray: np.ndarray, px: np.ndarray, board: BoardSpec) -> np.ndarray:
    """Chessboard corners [n, 2] reordered into the board frame (the detector's order may be
    mirrored or turned by 180 degrees): X runs along a row and Y down the rows as seen from the
    camera (X x Y away from it), and corner 0 is at the end whose outer corner square is black.
    """
    grid = px.reshape(board.rows, board.cols, 2)
    vx = (grid[:, -1] - grid[:, 0]).sum(0)
    vy = (grid[-1] - grid[0]).sum(0)
    if vx[0] * vy[1] - vx[1] * vy[0] < 0:  # image axes (col right, row down): mirrored
        grid = grid[:, ::-1]

    def outer_square(a, b, c):  # centre of the square diagonally outside corner a
        p = a + 0.5 * ((a - b) + (a - c))
        return float(cv2.getRectSubPix(gray, (3, 3), (float(p[0]), float(p[1]))).mean())

    first = outer_square(grid[0, 0], grid[0, 1], grid[1, 0])
    last = outer_square(grid[-1, -1], grid[-1, -2], grid[-2, -1])
    if first > last:
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2)


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Fitted camera.

    Attributes:
        camera_matrix: [3, 3] K, px.
        dist_coeffs: [n] OpenCV distortion (k1, k2, p1, p2, k3).
        image_size: (width, height) px.
        rms_px: overall reprojection error, RMS over every corner of every view, px.
        view_rms_px: [n_views] RMS reprojection error of each view, px.
        rvecs, tvecs: [n_views, 3] board -> camera pose of each view (Rodrigues, m).
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]
    rms_px: float
    view_rms_px: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray


def calibrate(detections: list[Detection], image_size: tuple[int, int],
              fit_k3: bool = False) -> Intrinsics:
    """Intrinsics and distortion from several views (k3 held at 0 unless `fit_k3`)."""
    obj = [d.object_points for d in detections]
    img = [d.image_points for d in detections]
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, image_size, None, None,
                                                         flags=flags, criteria=crit)
    except cv2.error as exc:
        raise CameraCalibrationError(f"calibration failed: {exc.err}") from None
    view_rms = np.array([
        view_error(d, k, dist, rv, tv) for d, rv, tv in zip(detections, rvecs, tvecs)])
    return Intrinsics(camera_matrix=np.asarray(k, float), dist_coeffs=np.asarray(dist).ravel(),
                      image_size=image_size, rms_px=float(rms), view_rms_px=view_rms,
                      rvecs=np.array([np.ravel(r) for r in rvecs]),
                      tvecs=np.array([np.ravel(t) for t in tvecs]))


def view_error(d: Detection, k, dist, rvec, tvec) -> float:
    """RMS distance between a view's detected corners and their reprojection, px."""
    proj, _ = cv2.projectPoints(d.object_points, rvec, tvec, k, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - d.image_px) ** 2, axis=1))))


def undistort_px(px: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Raw pixels [n, 2] -> undistorted pixels [n, 2] of the same camera matrix."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    p = np.asarray(px, np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(p, k, dist, P=k, criteria=crit).reshape(-1, 2)


@dataclass(frozen=True, slots=True)
class Plane:
    """The sample plane's square-on grid.

    Attributes:
        homography: [3, 3] undistorted camera pixel -> grid pixel.
        m_per_px: metres per grid pixel.
        origin_px: (col, row) of the sample origin in the grid.
        size_px: (width, height) of the grid.
        view_rms_px: reprojection error of the plane view with its fitted pose, px.
    """

    homography: np.ndarray
    m_per_px: float
    origin_px: tuple[float, float]
    size_px: tuple[int, int]
    view_rms_px: float


def sample_plane(board: BoardSpec, cam: Intrinsics, det: Detection,
                 m_per_px: float | None = None, max_size_factor: float = 2.0) -> Plane:
    """The square-on grid of the plane the target lies on in view `det`.

    The target's pose (`cv2.solvePnP` with the fitted camera) gives the map board (X, Y) ->
    undistorted pixel, K [r1 r2 t]; the grid is the sample frame (see the module docstring)
    scaled by 1 / m_per_px. Without `m_per_px` it keeps the camera's resolution over the
    target: the board's area in metres over its area in undistorted pixels, square-rooted.
    The grid covers the whole camera frame, cut to at most `max_size_factor` times the
    frame's width and height around the target (a very oblique view reaches far away).
    """
    k, dist = cam.camera_matrix, cam.dist_coeffs
    ok, rvec, tvec = cv2.solvePnP(det.object_points, det.image_points, k, dist,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CameraCalibrationError("cannot find the target's pose in the plane view")
    rvec, tvec = cv2.solvePnPRefineLM(det.object_points, det.image_points, k, dist, rvec, tvec)
    r = cv2.Rodrigues(rvec)[0]
    board_to_und = k @ np.column_stack([r[:, 0], r[:, 1], np.ravel(tvec)])
    w_m, h_m = board.extent_m
    quad = _apply(board_to_und, np.array([[0, 0], [w_m, 0], [w_m, h_m], [0, h_m]], float))
    if m_per_px is None:
        (a, b), (c, d) = quad[2] - quad[0], quad[3] - quad[1]
        area_px = 0.5 * abs(a * d - b * c)
        m_per_px = math.sqrt(w_m * h_m / area_px)
    x0, y0 = board.origin_m
    s = 1.0 / m_per_px
    # board (X, Y) -> grid (col, row) with the sample origin at grid (0, 0) for now
    board_to_grid = np.array([[s, 0.0, -x0 * s], [0.0, s, -y0 * s], [0.0, 0.0, 1.0]])
    hom = board_to_grid @ np.linalg.inv(board_to_und)
    w, h = cam.image_size
    edge = np.linspace(0.0, 1.0, 65)
    border = np.concatenate([
        np.column_stack([edge * (w - 1), np.zeros_like(edge)]),
        np.column_stack([edge * (w - 1), np.full_like(edge, h - 1)]),
        np.column_stack([np.zeros_like(edge), edge * (h - 1)]),
        np.column_stack([np.full_like(edge, w - 1), edge * (h - 1)])])
    border_und = undistort_px(border, k, dist)
    seen = _apply(hom, border_und)
    target = _apply(board_to_grid, np.array([[0, 0], [w_m, h_m]], float))
    centre_und = _apply(board_to_und, np.array([[w_m / 2, h_m / 2]]))
    if np.any(_w(hom, border_und) * _w(hom, centre_und)[0] <= 0):
        # the plane's horizon is in the frame: keep the box around the target
        seen = target
    lo, hi = np.floor(seen.min(0)), np.ceil(seen.max(0))
    centre = target.mean(0)
    half = max_size_factor * np.array([w, h], float) / 2
    lo = np.maximum(lo, np.floor(centre - half))
    hi = np.minimum(hi, np.ceil(centre + half))
    shift = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    hom = shift @ hom
    hom /= hom[2, 2]
    size = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
    err = view_error(det, k, dist, rvec, tvec)
    return Plane(homography=hom, m_per_px=float(m_per_px),
                 origin_px=(float(-lo[0]), float(-lo[1])), size_px=size, view_rms_px=err)


def _apply(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.column_stack([xy, np.ones(len(xy))]) @ h.T
    return p[:, :2] / p[:, 2:3]


def _w(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return (np.column_stack([xy, np.ones(len(xy))]) @ h.T)[:, 2]


def calibration_json(board: BoardSpec, cam: Intrinsics, plane: Plane, fps: float,
                     names: list[str], plane_name: str) -> dict:
    """The calibration file `metarig track` reads, with the camera model and its errors."""
    return {
        "fps": fps,
        "m_per_px": plane.m_per_px,
        "origin_px": list(plane.origin_px),
        "y_up": True,
        "homography": plane.homography.tolist(),
        "rectified_size_px": list(plane.size_px),
        "camera_matrix": cam.camera_matrix.tolist(),
        "dist_coeffs": cam.dist_coeffs.tolist(),
        "image_size_px": list(cam.image_size),
        "reprojection_error_px": {
            "overall_rms": cam.rms_px,
            "per_view": {n: float(e) for n, e in zip(names, cam.view_rms_px)},
            "plane_view": plane.view_rms_px,
        },
        "board": str(board),
        "plane_image": plane_name,
    }


def contact_sheet(images: list[np.ndarray], detections: list[Detection | None],
                  labels: list[str], tile_width: int = 400, columns: int = 3) -> np.ndarray:
    """BGR picture of every view with its detected corners (green; red title: none found)."""
    tiles = []
    for img, det, label in zip(images, detections, labels):
        scale = tile_width / img.shape[1]
        tile = cv2.resize(img, (tile_width, max(1, round(img.shape[0] * scale))),
                          interpolation=cv2.INTER_AREA)
        tile = cv2.cvtColor(tile, cv2.COLOR_GRAY2BGR)
        colour = (80, 80, 255) if det is None else (80, 255, 80)
        if det is not None:
            for c, r in (det.image_px + 0.5) * scale - 0.5:
                cv2.circle(tile, (round(c * 16), round(r * 16)), 3 * 16, (0, 255, 0), 1,
                           cv2.LINE_AA, shift=4)
        tile[:24] = 0
        cv2.putText(tile, label, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1,
                    cv2.LINE_AA)
        tiles.append(tile)
    th = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, th - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)
