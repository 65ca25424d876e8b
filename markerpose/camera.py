"""Cameras and the calibrated stereo rig.

``Camera`` is OpenCV's pinhole model with the distortion coefficients
(k1, k2, p1, p2, k3). ``StereoRig`` holds two cameras and the extrinsics
``R, t`` mapping left-camera coordinates to right-camera coordinates:
``X_right = R @ X_left + t`` (what ``cv2.stereoCalibrate`` returns), in mm.

Rig files are OpenCV FileStorage (YAML or XML) with the keys
``K1 dist1 K2 dist2 R t`` and optionally ``image_size`` (width, height) —
the layout of the original MarkerPose project's ``StereoParams.xml``.
All file reading and writing of rigs lives in this module.

Values that would load but cannot work are refused where the objects are built
(``Camera`` / ``StereoRig``), with a one-line ``ValueError`` naming the field, and
``StereoRig.load`` prefixes the file and key: K must be an upper-triangular intrinsic
matrix with entries within ``MAX_K_ENTRY`` px and condition number within ``MAX_K_COND``;
distortion coefficients finite and within ``MAX_DIST_COEFF``; ``image_size`` two whole
numbers in 1..``MAX_IMAGE_SIDE``; R a proper rotation; the baseline |t| within
``MIN_BASELINE``..``MAX_BASELINE`` mm.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from .jit import compiled

# Sanity limits for rigs: values outside them load but cannot work (overflow, division
# by ~0, singular matrices far from the code that reads the rig), so they are refused.
MAX_IMAGE_SIDE = 100_000  # px, per side
MAX_K_ENTRY = 1e8  # px: |fx|, |fy|, |skew|, |cx|, |cy|
MAX_K_COND = 1e12  # condition number of K (a typical K has ~3e3)
MAX_DIST_COEFF = 1e6  # |k1|, |k2|, |p1|, |p2|, |k3|
MIN_BASELINE = 1e-3  # mm
MAX_BASELINE = 1e9  # mm
ROTATION_TOL = 1e-6


def _as_matrix(value, shape, name) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.size != int(np.prod(shape)):
        raise ValueError(f"{name}: expected {int(np.prod(shape))} values for shape {shape}, got shape {a.shape}")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains non-finite values")
    return a


def _as_dist(value, name="dist") -> np.ndarray:
    """Distortion vector as (5,) k1 k2 p1 p2 k3; 4 coefficients are padded with k3 = 0.

    Longer OpenCV vectors (8, 12, 14) are accepted only if the extra terms are zero,
    because the rational / thin-prism / tilt models are not supported.
    """
    d = np.asarray(value, dtype=np.float64).ravel()
    if d.size == 4:
        d = np.append(d, 0.0)
    elif d.size > 5:
        if np.any(d[5:] != 0):
            raise ValueError(f"{name}: only k1 k2 p1 p2 k3 are supported; higher-order terms are non-zero")
        d = d[:5]
    elif d.size != 5:
        raise ValueError(f"{name}: expected 4 or 5 distortion coefficients (k1 k2 p1 p2 [k3]), got {d.size}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name}: contains non-finite values")
    if np.any(np.abs(d) > MAX_DIST_COEFF):
        raise ValueError(f"{name}: coefficient magnitude above {MAX_DIST_COEFF:g} is not a lens distortion, got {d.tolist()}")
    return d


def _as_intrinsics(value, name="K") -> np.ndarray:
    """(3, 3) pinhole intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, numerically invertible."""
    K = _as_matrix(value, (3, 3), name)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or K[2, 2] != 1 or np.any(K[2, :2] != 0):
        raise ValueError(f"{name}: not an intrinsic matrix (need fx, fy > 0, K[1,0] = 0 and last row 0 0 1), got {K.tolist()}")
    if np.abs(K).max() > MAX_K_ENTRY:
        raise ValueError(f"{name}: entries must be at most {MAX_K_ENTRY:g} px in magnitude, got {K.tolist()}")
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(K)
    if not cond <= MAX_K_COND:
        raise ValueError(f"{name}: numerically singular (condition number {cond:.3g} > {MAX_K_COND:g}), got {K.tolist()}")
    return K


def _as_volume(value, name: str = "volume") -> np.ndarray:
    """(2, 3) float64: the lowest and highest corner of a box, finite, lowest < highest."""
    try:
        v = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 2 x 3 numbers (lowest and highest corner, mm)") from None
    if v.size != 6 or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 2 x 3 finite numbers (lowest and highest corner, mm), got shape {v.shape}")
    v = v.reshape(2, 3)
    if not np.all(v[0] < v[1]):
        raise ValueError(f"{name}: the lowest corner {v[0].tolist()} must be below the highest {v[1].tolist()} on every axis")
    return v


def _as_image_size(value, name="image_size") -> tuple[int, int]:
    """(width, height) as Python ints in 1..MAX_IMAGE_SIDE; the values must be whole numbers."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected two numbers (width, height), got {value!r}") from None
    if a.size != 2:
        raise ValueError(f"{name}: expected two numbers (width, height), got shape {a.shape}")
    a = a.ravel()
    if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
        raise ValueError(f"{name}: width and height must be whole numbers of pixels, got {a.tolist()}")
    if np.any(a <= 0):
        # worded unlike its neighbours: callers match "<name> must be positive"
        raise ValueError(f"{name} must be positive (width, height), got {tuple(int(v) for v in a)}")
    if np.any(a > MAX_IMAGE_SIDE):
        raise ValueError(f"{name}: width and height must be at most {MAX_IMAGE_SIDE} px, got {a.tolist()}")
    return int(a[0]), int(a[1])


def _as_rotation(value, name="R") -> np.ndarray:
    """(3, 3) proper rotation: R @ R.T = I (atol ROTATION_TOL) and det(R) = +1."""
    R = _as_matrix(value, (3, 3), name)
    # Entries of a rotation are in [-1, 1]; checking that first also keeps R @ R.T from overflowing.
    ok = np.abs(R).max() <= 1 + 1e-3
    ok = ok and np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOL)  # default rtol
    ok = ok and abs(np.linalg.det(R) - 1) <= 1e-3  # orthonormal: det is ±1, so this refuses reflections
    if not ok:
        raise ValueError(f"{name}: not a rotation matrix (R @ R.T != I or det(R) != 1)")
    return R


def _as_translation(value, name="t") -> np.ndarray:
    """(3,) translation, mm, with a baseline |t| in MIN_BASELINE..MAX_BASELINE."""
    t = _as_matrix(value, (3,), name)
    m = float(np.abs(t).max())
    b = m * float(np.linalg.norm(t / m)) if m > 0 else 0.0  # scaled: no overflow for huge t
    if not b >= MIN_BASELINE:
        raise ValueError(f"{name}: baseline |t| = {b:.3g} mm is below {MIN_BASELINE:g} mm (the two cameras coincide)")
    if not b <= MAX_BASELINE:
        raise ValueError(f"{name}: baseline |t| = {b:.3g} mm is above {MAX_BASELINE:g} mm")
    return t


@dataclass
class Camera:
    """Pinhole camera with OpenCV radial-tangential distortion.

    Attributes:
        K: (3, 3) intrinsic matrix, pixels.
        dist: (5,) k1 k2 p1 p2 k3.
        image_size: (width, height) in pixels, or None if unknown.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    image_size: tuple[int, int] | None = None

    def __post_init__(self):
        self.K = _as_intrinsics(self.K, "K")
        self.dist = _as_dist(self.dist)
        if self.image_size is not None:
            self.image_size = _as_image_size(self.image_size)

    # --- projection ---------------------------------------------------------------
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Apply the distortion model to normalised coordinates and map to pixels.

        Args:
            xn: (N, 2) ideal normalised image coordinates (x/z, y/z).
        Returns:
            (N, 2) distorted pixel coordinates.
        """
        xn = np.ascontiguousarray(xn, dtype=np.float64).reshape(-1, 2)
        out = np.empty_like(xn)
        _distort(xn, self.K, self.dist, out)
        return out

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project 3D points given in this camera's frame.

        Args:
            points: (N, 3) points, mm, in front of the camera (z > 0).
        Returns:
            (N, 2) distorted pixel coordinates.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.distort(p[:, :2] / p[:, 2:3])

    def undistort_points(self, pixels: np.ndarray, ideal_pixels: bool = True) -> np.ndarray:
        """Remove lens distortion from pixel coordinates.

        Newton's method on the distortion model, per point, until the re-distorted
        position is within 1e-7 px, and one step more (OpenCV's default five fixed-point
        iterations are far from that in the corners of a wide lens). Where Newton does not
        converge within 30 steps or leaves the lens's branch, OpenCV's fixed-point iteration (``cv2.undistortPointsIter`` on OpenCV 4,
        ``cv2.undistortPoints`` with criteria on OpenCV 5): 20 iterations, and 200 more
        for the points still off by more than 1e-7 px.

        Args:
            pixels: (N, 2) distorted pixel coordinates.
            ideal_pixels: return ideal pixels ``K @ xn`` (True) or normalised coordinates (False).
        Returns:
            (N, 2) undistorted coordinates.
        """
        px = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        xn, ok = np.empty_like(px), np.empty(len(px), bool)
        _undistort(px, self.K, self.dist, xn, ok)
        if not ok.all():  # Newton did not converge (far outside the lens's field): OpenCV's iteration
            bad = ~ok
            xn[bad] = self._undistort_normalized(px[bad].reshape(-1, 1, 2), 20)
            worse = bad & (np.abs(self.distort(xn) - px).max(axis=1) > 1e-7)
            if worse.any():
                xn[worse] = self._undistort_normalized(px[worse].reshape(-1, 1, 2), 200)
        if not ideal_pixels:
            return xn
        return xn @ self.K[:2, :2].T + self.K[:2, 2]

    def _undistort_normalized(self, px: np.ndarray, iterations: int) -> np.ndarray:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-15)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            out = cv2.undistortPointsIter(px, self.K, self.dist, None, None, crit)
        else:  # OpenCV 5 folded the criteria into undistortPoints
            out = cv2.undistortPoints(px, self.K, self.dist, R=None, P=None, criteria=crit)
        return out.reshape(-1, 2)

    def normalized_grid(self) -> np.ndarray:
        """(H, W, 2) ideal normalised coordinates of every pixel centre (cached).

        The inverse of the distortion model, solved to ~1e-10 px; the renderer
        casts its rays through it.
        """
        if self.image_size is None:
            raise ValueError("camera has no image_size")
        key = (self.K.tobytes(), self.dist.tobytes(), self.image_size)
        cache = getattr(self, "_grid_cache", None)
        if cache is not None and cache[0] == key:
            return cache[1]
        w, h = self.image_size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        grid = self.undistort_points(np.column_stack([u.ravel(), v.ravel()]), ideal_pixels=False)
        grid = grid.reshape(h, w, 2)
        object.__setattr__(self, "_grid_cache", (key, grid))
        return grid


@compiled
def distort_point(x, y, K, dist):  # pragma: no cover - compiled
    """The distorted pixel (u, v) of the normalised point (x, y): the lens model of
    :meth:`Camera.distort` for one point, callable from other compiled loops."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]


@compiled
def undistort_point(u, v, K, dist):  # pragma: no cover - compiled
    """The normalised point (x, y) whose distorted pixel is (u, v), by Newton's method from
    the distorted point, and whether it converged (re-distorted within 1e-7 px): one point
    of :meth:`Camera.undistort_points`, callable from other compiled loops."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    yt = (v - cy) / fy
    xt = (u - cx - skew * yt) / fx
    x, y = xt, yt
    ok = False
    for _ in range(30):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ex = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xt
        ey = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yt
        if abs(fx * ex + skew * ey) <= 1e-7 and abs(fy * ey) <= 1e-7:
            # Converged in pixels; one more step takes it to the float limit.
            ok = True
        dr = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d radial / d r2, times 2
        a = radial + x * x * dr + 2 * p1 * y + 6 * p2 * x
        b = x * y * dr + 2 * p1 * x + 2 * p2 * y
        d = radial + y * y * dr + 6 * p1 * y + 2 * p2 * x
        det = a * d - b * b
        if not det > 0:  # past the lens's fold (or not finite): not the physical branch
            return x, y, False
        x, y = x - (d * ex - b * ey) / det, y - (a * ey - b * ex) / det
        if ok:
            break
    return x, y, ok


@compiled
def _distort(xn, K, dist, out):  # pragma: no cover - compiled
    """:meth:`Camera.distort` of each row of ``xn`` into ``out``."""
    for i in range(xn.shape[0]):
        out[i, 0], out[i, 1] = distort_point(xn[i, 0], xn[i, 1], K, dist)


@compiled
def _undistort(px, K, dist, xn, ok):  # pragma: no cover - compiled
    """:func:`undistort_point` of each row of ``px`` into ``xn`` and ``ok``."""
    for i in range(px.shape[0]):
        xn[i, 0], xn[i, 1], ok[i] = undistort_point(px[i, 0], px[i, 1], K, dist)


_WARM = False


def warm_up() -> None:
    """Compile the projection kernels (or load them from numba's cache) once per process."""
    global _WARM
    if not _WARM:
        cam = Camera(np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), [0.1, 0, 0, 0, 0])
        cam.undistort_points(cam.distort(np.zeros((1, 2))))
        _WARM = True


def _look_at(center: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation camera→world for a camera at ``center`` looking at ``target`` (y down in the image)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # image x to the right when y is down
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


@functools.lru_cache(maxsize=16)
def _rig_matrices(K1: bytes, K2: bytes, R: bytes, t: bytes) -> tuple:
    """(T_right_left, P1, P2) of a rig given as its arrays' bytes (float64), read-only."""
    K1, K2, R, t = np.frombuffer(K1).reshape(3, 3), np.frombuffer(K2).reshape(3, 3), np.frombuffer(R).reshape(3, 3), np.frombuffer(t)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    out = (T, K1 @ np.hstack([np.eye(3), np.zeros((3, 1))]), K2 @ np.hstack([R, t.reshape(3, 1)]))
    for a in out:
        a.flags.writeable = False
    return out


@dataclass
class StereoRig:
    """Two calibrated cameras; ``X_right = R @ X_left + t`` (mm).

    Attributes:
        left, right: the cameras.
        R: (3, 3) rotation left→right.
        t: (3,) translation left→right, mm; the baseline |t| must be in
            ``MIN_BASELINE..MAX_BASELINE`` (1e-3..1e9 mm), so the default zeros are refused.
        volume: optional (2, 3) the calibrated volume: the lowest and highest corner, in the
            left-camera frame (mm), of the box the calibration grid's points filled
            (``markerpose calibrate`` writes it); None where unknown.

    Invalid values (also ``Camera``'s: K, dist, image_size) raise ``ValueError`` naming the field.
    """

    left: Camera
    right: Camera
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    volume: np.ndarray | None = None

    def __post_init__(self):
        self.R = _as_rotation(self.R, "R")
        self.t = _as_translation(self.t, "t")
        if self.volume is not None:
            self.volume = _as_volume(self.volume)

    def in_volume(self, points_left, margin: float = 0.1) -> bool:
        """Whether every point (N, 3, left-camera frame, mm) lies in the calibrated volume
        enlarged by ``margin`` of its size on every side (True where the volume is unknown)."""
        if self.volume is None:
            return True
        lo, hi = self.volume
        pad = margin * (hi - lo)
        p = np.asarray(points_left, np.float64).reshape(-1, 3)
        return bool(np.all((p >= lo - pad) & (p <= hi + pad)))

    @property
    def cameras(self) -> tuple[Camera, Camera]:
        return (self.left, self.right)

    def _matrices(self) -> tuple:
        """(T_right_left, P1, P2) of the rig as it is now (computed once per state: the
        solve and the checks ask for them at every pose)."""
        return _rig_matrices(*(np.asarray(a, np.float64).tobytes() for a in (self.left.K, self.right.K, self.R, self.t)))

    @property
    def T_right_left(self) -> np.ndarray:
        """(4, 4) transform from left-camera to right-camera coordinates."""
        return self._matrices()[0].copy()

    @property
    def P1(self) -> np.ndarray:
        """(3, 4) projection matrix of the left camera (ideal pixels), ``K1 [I | 0]``."""
        return self._matrices()[1].copy()

    @property
    def P2(self) -> np.ndarray:
        """(3, 4) projection matrix of the right camera (ideal pixels), ``K2 [R | t]``."""
        return self._matrices()[2].copy()

    @property
    def baseline(self) -> float:
        """Distance between the optical centres, mm."""
        return float(np.linalg.norm(self.t))

    def to_right(self, points_left: np.ndarray) -> np.ndarray:
        """(N, 3) left-camera points → (N, 3) right-camera points."""
        p = np.asarray(points_left, dtype=np.float64).reshape(-1, 3)
        return p @ self.R.T + self.t

    def project(self, points_left: np.ndarray) -> np.ndarray:
        """Project left-frame 3D points into both views.

        Args:
            points_left: (N, 3) points in the left-camera frame, mm.
        Returns:
            (2, N, 2) distorted pixel coordinates [view][point][x, y].
        """
        p = np.asarray(points_left, dtype=np.float64).reshape(-1, 3)
        return np.stack([self.left.project(p), self.right.project(self.to_right(p))])

    # --- file I/O -----------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> StereoRig:
        """Read a rig from OpenCV FileStorage YAML or XML (keys ``K1 dist1 K2 dist2 R t``).

        Raises:
            FileNotFoundError: the file does not exist.
            ValueError: the file cannot be parsed, or a key is missing or malformed (named).
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"rig file not found: {path}")
        from .formats import open_storage, storage_array

        fs = open_storage(path)
        try:
            vals = {}
            for key in ("K1", "dist1", "K2", "dist2", "R", "t"):
                m = storage_array(fs, key, path)
                if m is None:
                    raise ValueError(f"{path}: missing key '{key}'")
                vals[key] = m
            bad_size = f"{path}: key 'image_size' must hold two numbers (width, height)"
            try:
                arr = storage_array(fs, "image_size", path)
            except ValueError:
                raise ValueError(bad_size) from None
            if arr is not None:
                if arr.size != 2:
                    raise ValueError(bad_size)
                vals["image_size"] = arr.ravel()
            vol = storage_array(fs, "volume", path)
            if vol is not None:
                vals["volume"] = vol
        finally:
            fs.release()

        def build(key, fn, *args):
            try:
                return fn(vals[key], *args)
            except ValueError as e:
                raise ValueError(f"{path}: key '{key}' is malformed: {e}") from None

        # Every key is validated on its own (the same checks Camera / StereoRig run), so
        # that an error names the key it comes from.
        K1 = build("K1", _as_intrinsics, "K1")
        K2 = build("K2", _as_intrinsics, "K2")
        d1 = build("dist1", _as_dist, "dist1")
        d2 = build("dist2", _as_dist, "dist2")
        R = build("R", _as_rotation, "R")
        t = build("t", _as_translation, "t")
        size = build("image_size", _as_image_size, "image_size") if "image_size" in vals else None
        volume = build("volume", _as_volume) if "volume" in vals else None
        try:
            return cls(Camera(K1, d1, size), Camera(K2, d2, size), R, t, volume)
        except ValueError as e:  # not expected: the keys passed the same checks above
            raise ValueError(f"{path}: {e}") from None

    def save(self, path: str | Path) -> Path:
        """Write the rig as OpenCV FileStorage; the format follows the suffix (.yaml/.yml/.xml)."""
        path = Path(path)
        if path.suffix.lower() not in (".yaml", ".yml", ".xml"):
            raise ValueError(f"rig file must end in .yaml, .yml or .xml, got {path.name}")
        path.parent.mkdir(parents=True, exist_ok=True)
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise ValueError(f"cannot write the rig file {path}")
        fs.write("K1", self.left.K)
        fs.write("dist1", self.left.dist.reshape(1, 5))
        fs.write("K2", self.right.K)
        fs.write("dist2", self.right.dist.reshape(1, 5))
        fs.write("R", self.R)
        fs.write("t", self.t.reshape(3, 1))
        if self.left.image_size is not None:
            fs.write("image_size", np.array(self.left.image_size, dtype=np.int32).reshape(1, 2))
        if self.volume is not None:
            fs.write("volume", self.volume)
        fs.release()
        return path

    @classmethod
    def default(cls) -> StereoRig:
        """The simulated paper-like rig shipped with the package (``data/default_rig.yaml``).

        Two 1280x1024 mono cameras with 4.8 µm pixels and 12 mm lenses (f ≈ 2500 px),
        175 mm apart and toed in toward a point 560 mm in front of the rig, so both
        views see the marker from 350 to 800 mm; mild barrel distortion.
        ``build_default_rig()`` is how that file was made.
        """
        with resources.as_file(resources.files("markerpose") / "data" / "default_rig.yaml") as p:
            return cls.load(p)


def build_default_rig() -> StereoRig:
    """Construct the default rig from its physical description (see ``StereoRig.default``)."""
    size = (1280, 1024)
    f_px = 12.0 / 4.8e-3  # focal length / pixel pitch = 2500 px
    K1 = np.array([[f_px * 1.0008, 0, 643.7], [0, f_px * 1.0003, 508.2], [0, 0, 1]])
    K2 = np.array([[f_px * 0.9991, 0, 636.1], [0, f_px * 0.9995, 515.9], [0, 0, 1]])
    d1 = np.array([-0.082, 0.141, 2.1e-4, -1.4e-4, 0.0])
    d2 = np.array([-0.076, 0.118, -1.7e-4, 2.6e-4, 0.0])
    baseline, converge = 175.0, 560.0
    target = np.array([0.0, 0.0, converge])
    c_l, c_r = np.array([-baseline / 2, 0, 0]), np.array([baseline / 2, 0, 0])
    Rw_l, Rw_r = _look_at(c_l, target), _look_at(c_r, target)  # camera → rig
    # X_rig = Rw_l X_l + c_l ; X_r = Rw_r^T (X_rig - c_r)
    R = Rw_r.T @ Rw_l
    t = Rw_r.T @ (c_l - c_r)
    return StereoRig(Camera(K1, d1, size), Camera(K2, d2, size), R, t)
