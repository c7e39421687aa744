"""Camera models, undistortion to a pinhole camera, photometric calibration.

Calibration *files* are read in :mod:`mgso.io` (``mgso.io.calibration`` for DSO ``camera.txt`` and plain intrinsics,
each dataset's own format beside its reader); this module never imports :mod:`mgso.io`.

Conventions (used everywhere in mgso):

- **Pixel centres are at integer coordinates**: the centre of pixel ``(0, 0)`` is at ``(0.0, 0.0)``; the image covers
  ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. This is OpenCV's and DSO's convention. Calibrations given in "relative"
  form (DSO camera.txt with ``cx, cy < 1``: fractions of the image size, pixel ``(0, 0)`` covering ``[0, 1]^2``) are
  converted with DSO's rule ``fx = fx_rel * W``, ``cx = cx_rel * W - 0.5``.
- Camera frame x right, y down, z forward. A model maps a point ``P`` to the *normalised* undistorted coordinates
  ``xn = (X / Z, Y / Z)``, distorts them to ``xd = d(xn)`` and returns the pixel ``(fx * xd_x + cx, fy * xd_y + cy)``.
- After undistortion the rest of the system sees a :class:`PinholeCamera` (``fx, fy, cx, cy, width, height``).
  Scaling it (pyramid levels) keeps the pixel-centre convention: ``cx' = (cx + 0.5) * s - 0.5``.

Models (``d(xn)``):

- :class:`PinholeCamera`: no distortion.
- :class:`RadTanCamera`: OpenCV radial-tangential ``k1 k2 p1 p2 [k3]`` (DSO ``RadTan``, EuRoC ``radial-tangential``).
- :class:`EquidistantCamera`: Kannala-Brandt ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``, which is the
  same function as OpenCV's ``cv2.fisheye`` model and DSO's ``EquiDistant`` and ``KannalaBrandt`` (identical there).
- :class:`FOVCamera`: Devernay-Faugeras FOV / ATAN (PTAM, DSO ``FOV``): ``r_d = atan(2 r tan(omega / 2)) / omega``.

Undistortion (:class:`Undistorter`) builds remap tables once (OpenCV's ``initUndistortRectifyMap`` for RadTan,
``cv2.fisheye.initUndistortRectifyMap`` for equidistant, our own for FOV) and applies ``cv2.remap`` per frame
(bilinear; output pixels without a source hold the nearest input pixel and are False in ``valid_mask``). A pinhole input without distortion whose output camera equals the input camera is
passed through untouched (bit-exact, no copy); one that only changes size is resized (``cv2.resize``, area filter when
shrinking), with intrinsics scaled by the pixel-centre rule.

Output cameras (DSO ``camera.txt`` line 3): ``keep`` (ours, the default for a distorted lens: the field of view of
``full``, pulled in only until every pixel without a source lies in the outer :data:`KEEP_BORDER_PX` rows and columns,
which the odometry ignores), ``crop`` (a rectangle of valid pixels, no black border; DSO's search, reimplemented,
which zooms a pincushion lens such as TUM freiburg1 1.37x), ``full`` (the whole input visible: bounding box of the undistorted image border), ``none``
(the input intrinsics scaled to the output size; for a distorted lens the image is still undistorted, unlike DSO,
which silently keeps the distortion), or explicit ``fx fy cx cy 0`` (relative when ``cx, cy < 1``, else absolute).

Photometric calibration (TUM monoVO, DSO's model ``I_raw = G(t V(x) B(x))``): :meth:`PhotometricCalibration.apply`
returns ``G^-1(I_raw) / V(x)`` in DSO's 0-255 scale; the exposure time ``t`` is *not* divided out but reported with the
frame, so that the tracker's affine brightness model can use it (as DSO does). The vignette is applied **before**
undistortion, in the input image geometry (as DSO does), so it is never remapped.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Union

import cv2
import numpy as np

__all__ = [
    "CalibrationError", "CameraModel", "PinholeCamera", "RadTanCamera", "EquidistantCamera", "FOVCamera",
    "OutputSpec", "CameraSpec", "Undistorter", "PhotometricCalibration", "Calibration", "RECTIFY_MODES",
    "KEEP_BORDER_PX", "crop_output_camera", "full_output_camera", "keep_output_camera", "make_output_camera",
    "output_camera_and_mode", "read_inverse_response", "read_vignette",
]

log = logging.getLogger(__name__)

RECTIFY_MODES = ("keep", "crop", "full", "none")
#: ``keep``: output pixels without a source in the input may only lie this many pixels from the image border (rows and
#: columns 0..2 and W-3..W-1): DSO's pixel selection never takes a pixel within 4 px of the border, nor reads a
#: gradient there (central differences of pixels 3..5 for pixel 4), so such a border costs the odometry nothing.
KEEP_BORDER_PX = 3


class CalibrationError(ValueError):
    """A calibration file or value is missing or malformed; the message names the file and the problem."""


# ================================================================================================ camera models
def _as_points(x, n: int, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"{what}: expected an (N, {n}) array, got shape {np.shape(x)}")
    return a


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics ``fx fy cx cy`` (pixels, pixel centres at integers) and image size, plus a lens distortion.

    Subclasses define ``distort_normalized`` / ``undistort_normalized`` (normalised undistorted <-> normalised
    distorted coordinates) and ``max_radius`` (the normalised undistorted radius beyond which the model is not
    invertible, e.g. where a radial polynomial folds back; ``inf`` when it never does).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    model_name: ClassVar[str] = "abstract"

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise CalibrationError(f"{type(self).__name__}: {name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"{type(self).__name__}: focal lengths must be positive, got fx={self.fx}, "
                                   f"fy={self.fy}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, float) and v.is_integer():
                v = int(v)
            if not isinstance(v, (int, np.integer)) or v <= 0:
                raise CalibrationError(f"{type(self).__name__}: {name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in self.distortion_names():
            v = getattr(self, name)
            if not math.isfinite(float(v)):
                raise CalibrationError(f"{type(self).__name__}: {name} must be finite, got {v!r}")
            object.__setattr__(self, name, float(v))

    # ---------------------------------------------------------------- description
    @classmethod
    def distortion_names(cls) -> tuple[str, ...]:
        base = {"fx", "fy", "cx", "cy", "width", "height"}
        return tuple(f.name for f in dataclasses.fields(cls) if f.name not in base)

    @property
    def distortion(self) -> dict[str, float]:
        """The distortion parameters by name (empty for a pinhole)."""
        return {n: getattr(self, n) for n in self.distortion_names()}

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.distortion.values())

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (self.width, self.height)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def pinhole(self) -> "PinholeCamera":
        """The same intrinsics and size without the distortion."""
        return PinholeCamera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def resized(self, width: int, height: int):
        """The same lens at another image size (intrinsics scaled by the pixel-centre rule; distortion, which acts
        on normalised coordinates, unchanged)."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                                   cy=(self.cy + 0.5) * sy - 0.5, width=int(width), height=int(height))

    # ---------------------------------------------------------------- model
    @property
    def max_radius(self) -> float:
        """Normalised undistorted radius beyond which the distortion is not invertible (``inf``: never)."""
        return math.inf

    def distort_normalized(self, xn: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def undistort_normalized(self, xd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`distort_normalized`: ``(xn (N, 2), valid (N,))``."""
        raise NotImplementedError

    def pixel_from_normalized(self, xn) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted ``(N, 2)`` -> pixels ``(N, 2)`` and a validity mask (inside the invertible
        region of the model; not checked against the image bounds)."""
        xn = _as_points(xn, 2, "pixel_from_normalized")
        valid = np.hypot(xn[:, 0], xn[:, 1]) < self.max_radius
        xd = self.distort_normalized(xn)
        uv = np.empty_like(xd)
        uv[:, 0] = self.fx * xd[:, 0] + self.cx
        uv[:, 1] = self.fy * xd[:, 1] + self.cy
        return uv, valid & np.all(np.isfinite(uv), axis=1)

    def normalized_from_pixel(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(N, 2)`` -> normalised undistorted ``(N, 2)`` and a validity mask."""
        uv = _as_points(uv, 2, "normalized_from_pixel")
        xd = np.empty_like(uv)
        xd[:, 0] = (uv[:, 0] - self.cx) / self.fx
        xd[:, 1] = (uv[:, 1] - self.cy) / self.fy
        return self.undistort_normalized(xd)

    def project(self, points_cam) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points ``(N, 3)`` -> pixels ``(N, 2)`` and a mask (in front of the camera and inside the
        model's invertible region; not checked against the image bounds, see :meth:`in_image`)."""
        p = _as_points(points_cam, 3, "project")
        z = p[:, 2]
        front = z > 1e-12
        zs = np.where(front, z, 1.0)
        xn = p[:, :2] / zs[:, None]
        uv, valid = self.pixel_from_normalized(xn)
        return uv, valid & front

    def unproject(self, uv, depth=None) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(N, 2)`` -> camera-frame points ``(N, 3)`` on the ``z = 1`` plane (or at ``depth`` (N,), the
        z coordinate) and a validity mask."""
        xn, valid = self.normalized_from_pixel(uv)
        rays = np.concatenate([xn, np.ones((len(xn), 1))], axis=1)
        if depth is not None:
            rays = rays * np.asarray(depth, dtype=np.float64).reshape(-1, 1)
        return rays, valid

    def in_image(self, uv, border: float = 0.0) -> np.ndarray:
        """Mask of pixels ``(N, 2)`` inside ``[border, W - 1 - border] x [border, H - 1 - border]``."""
        uv = _as_points(uv, 2, "in_image")
        return ((uv[:, 0] >= border) & (uv[:, 0] <= self.width - 1 - border)
                & (uv[:, 1] >= border) & (uv[:, 1] <= self.height - 1 - border))

    def describe(self) -> dict:
        return {"model": self.model_name, "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "distortion": self.distortion}


@dataclass(frozen=True)
class PinholeCamera(CameraModel):
    """The undistorted camera the rest of the system uses: ``u = fx X/Z + cx``, ``v = fy Y/Z + cy``.

    Pixel centres at integer coordinates (pixel (0, 0) centre at (0, 0)).
    """

    model_name: ClassVar[str] = "pinhole"

    @property
    def K_inv(self) -> np.ndarray:
        return np.array([[1.0 / self.fx, 0.0, -self.cx / self.fx], [0.0, 1.0 / self.fy, -self.cy / self.fy],
                         [0.0, 0.0, 1.0]])

    def distort_normalized(self, xn):
        return np.array(xn, dtype=np.float64, copy=True)

    def undistort_normalized(self, xd):
        xd = np.array(xd, dtype=np.float64, copy=True)
        return xd, np.all(np.isfinite(xd), axis=1)

    def scaled(self, factor: float) -> "PinholeCamera":
        """The camera of an image scaled by ``factor`` (0.5 = next pyramid level).

        Pixel-centre rule: pixel ``j`` of a 2x2-averaged level covers pixels ``2j, 2j+1`` whose centres average to
        ``2j + 0.5``, hence ``cx' = (cx + 0.5) * factor - 0.5`` (DSO's pyramid rule). Sizes are floored, as a 2x2
        averaging pyramid drops an odd last row or column.
        """
        if not factor > 0:
            raise ValueError(f"scale factor must be positive, got {factor}")
        w = max(1, int(math.floor(self.width * factor + 1e-9)))
        h = max(1, int(math.floor(self.height * factor + 1e-9)))
        return PinholeCamera(self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                             (self.cy + 0.5) * factor - 0.5, w, h)

    def pyramid_level(self, level: int) -> "PinholeCamera":
        """The camera of pyramid level ``level`` (0 = this one; each level halves the size, floored)."""
        cam = self
        for _ in range(int(level)):
            cam = cam.scaled(0.5)
        return cam


@dataclass(frozen=True)
class RadTanCamera(CameraModel):
    """OpenCV radial-tangential distortion (Brown-Conrady): ``k1 k2 p1 p2 [k3]``.

    ``xd = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)``,
    ``yd = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y``.
    """

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    model_name: ClassVar[str] = "radtan"

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV order ``(k1, k2, p1, p2, k3)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def max_radius(self) -> float:
        # r (1 + k1 r^2 + k2 r^4 + k3 r^6) stops increasing where 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 = 0 (s = r^2).
        return _first_positive_root_sqrt([7 * self.k3, 5 * self.k2, 3 * self.k1, 1.0])

    def distort_normalized(self, xn):
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([xd, yd], axis=1)

    def undistort_normalized(self, xd):
        xd = _as_points(xd, 2, "undistort_normalized")
        x, y = xd[:, 0].copy(), xd[:, 1].copy()
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        for _ in range(30):  # Newton on the 2x2 system; converges in a few steps inside the monotone region
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd[:, 0]
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - xd[:, 1]
            j11 = radial + 2.0 * x * x * dradial_dr2 + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * dradial_dr2 + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = 2.0 * x * y * dradial_dr2 + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * dradial_dr2 + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x - (j22 * fx_ - j12 * fy_) / det
            y = y - (-j21 * fx_ + j11 * fy_) / det
        xn = np.stack([x, y], axis=1)
        back = self.distort_normalized(xn)
        valid = (np.all(np.isfinite(xn), axis=1) & (np.hypot(x, y) < self.max_radius)
                 & (np.max(np.abs(back - xd), axis=1) < 1e-9))
        return xn, valid


@dataclass(frozen=True)
class EquidistantCamera(CameraModel):
    """Kannala-Brandt / OpenCV fisheye / DSO EquiDistant: ``theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 +
    k4 t^8)`` with ``theta = atan(r)``, ``xd = xn theta_d / r``."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    model_name: ClassVar[str] = "equidistant"

    @property
    def has_distortion(self) -> bool:
        return True  # even with k = 0 the equidistant projection (theta_d = theta) is not a pinhole

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.k3, self.k4])

    @property
    def max_theta(self) -> float:
        t = _first_positive_root_sqrt([9 * self.k4, 7 * self.k3, 5 * self.k2, 3 * self.k1, 1.0])
        return min(t, math.pi / 2)

    @property
    def max_radius(self) -> float:
        t = self.max_theta
        return math.inf if t >= math.pi / 2 else math.tan(t)

    def _theta_d(self, theta):
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def distort_normalized(self, xn):
        r = np.hypot(xn[:, 0], xn[:, 1])
        theta = np.arctan(r)
        safe = r > 1e-12
        scale = np.where(safe, self._theta_d(theta) / np.where(safe, r, 1.0), 1.0)
        return xn * scale[:, None]

    def undistort_normalized(self, xd):
        xd = _as_points(xd, 2, "undistort_normalized")
        rd = np.hypot(xd[:, 0], xd[:, 1])
        tmax = self.max_theta
        theta = np.minimum(rd, tmax)
        for _ in range(30):
            t2 = theta * theta
            f = self._theta_d(theta) - rd
            df = 1.0 + t2 * (3 * self.k1 + t2 * (5 * self.k2 + t2 * (7 * self.k3 + t2 * 9 * self.k4)))
            theta = np.clip(theta - f / np.where(np.abs(df) < 1e-12, 1e-12, df), 0.0, tmax)
        ok = (np.abs(self._theta_d(theta) - rd) < 1e-9) & (theta < min(tmax, math.pi / 2 - 1e-9))
        r = np.tan(np.where(ok, theta, 0.0))
        safe = rd > 1e-12
        scale = np.where(safe, r / np.where(safe, rd, 1.0), 1.0)
        return xd * scale[:, None], ok


@dataclass(frozen=True)
class FOVCamera(CameraModel):
    """Devernay-Faugeras FOV model (PTAM's ATAN, DSO's FOV): ``r_d = atan(2 r tan(omega / 2)) / omega``."""

    omega: float = 0.0

    model_name: ClassVar[str] = "fov"

    def __post_init__(self):
        super().__post_init__()
        if not (0.0 <= self.omega < math.pi):
            raise CalibrationError(f"FOVCamera: omega must be in [0, pi), got {self.omega}")

    def distort_normalized(self, xn):
        if self.omega == 0.0:
            return np.array(xn, dtype=np.float64, copy=True)
        r = np.hypot(xn[:, 0], xn[:, 1])
        k = 2.0 * math.tan(self.omega / 2.0)
        safe = r > 1e-12
        rs = np.where(safe, r, 1.0)
        scale = np.where(safe, np.arctan(rs * k) / (self.omega * rs), k / self.omega)
        return xn * scale[:, None]

    def undistort_normalized(self, xd):
        xd = _as_points(xd, 2, "undistort_normalized")
        if self.omega == 0.0:
            return xd.copy(), np.all(np.isfinite(xd), axis=1)
        rd = np.hypot(xd[:, 0], xd[:, 1])
        k = 2.0 * math.tan(self.omega / 2.0)
        ang = rd * self.omega
        ok = ang < math.pi / 2 - 1e-9
        safe = rd > 1e-12
        rds = np.where(safe, rd, 1.0)
        scale = np.where(safe, np.tan(np.where(ok, ang, 0.0)) / (k * rds), self.omega / k)
        return xd * scale[:, None], ok


def _first_positive_root_sqrt(coeffs) -> float:
    """sqrt of the smallest positive real root of the polynomial (highest power first), or inf."""
    c = np.trim_zeros(np.asarray(coeffs, dtype=np.float64), "f")
    if len(c) <= 1:
        return math.inf
    roots = np.roots(c)
    real = roots[(np.abs(roots.imag) < 1e-9) & (roots.real > 0)].real
    return float(np.sqrt(real.min())) if len(real) else math.inf


# ============================================================================================== output cameras
@dataclass(frozen=True)
class OutputSpec:
    """What a calibration file asks of the undistorted output: a mode and a size.

    ``mode``: ``crop`` | ``full`` | ``none`` | ``explicit``. For ``explicit``, ``intrinsics`` holds ``fx fy cx cy``,
    relative to the output size when ``relative`` (DSO's form) else in pixels. ``size`` ``None`` = the input size.
    """

    mode: str = "none"
    size: tuple[int, int] | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    relative: bool = False

    def __post_init__(self):
        if self.mode not in RECTIFY_MODES + ("explicit",):
            raise CalibrationError(f"output mode must be one of {RECTIFY_MODES + ('explicit',)}, got {self.mode!r}")
        if (self.mode == "explicit") != (self.intrinsics is not None):
            raise CalibrationError("explicit output needs intrinsics (and only explicit output takes them)")


def _valid_in_input(model: CameraModel, xn: np.ndarray) -> np.ndarray:
    """Normalised points whose distorted pixel lies strictly inside the input image (DSO's (0, W-1) test)."""
    uv, ok = model.pixel_from_normalized(xn)
    return ok & (uv[:, 0] > 0) & (uv[:, 0] < model.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < model.height - 1)


def _axis_run(model: CameraModel, axis: int, extent: float = 10.0, samples: int = 200001) -> tuple[float, float]:
    s = np.linspace(-extent, extent, samples)
    pts = np.zeros((samples, 2))
    pts[:, axis] = s
    ok = _valid_in_input(model, pts)
    c = samples // 2
    if not ok[c]:
        raise CalibrationError(f"crop: the principal point of {model.model_name} camera {model.describe()} is "
                               "not inside the image")
    lo = c
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    hi = c
    while hi < samples - 1 and ok[hi + 1]:
        hi += 1
    return float(s[lo]), float(s[hi])


def crop_output_camera(model: CameraModel, width: int, height: int) -> PinholeCamera:
    """The pinhole camera of size ``width x height`` that sees the largest axis-aligned rectangle of the undistorted
    image containing only valid pixels (no black border).

    Same search as DSO's ``makeOptimalK_crop`` (reimplemented): stretch the horizontal and vertical lines through the
    principal point as far as they stay inside the input image, widen that box by 1 %, then shrink by 0.5 % a step
    every side whose edge still samples a pixel outside the input (only the sides of the wider dimension when both
    dimensions have offenders), until none does. The box edges become output pixels 0 and W-1 (H-1).
    """
    x0, x1 = _axis_run(model, 0)
    y0, y1 = _axis_run(model, 1)
    x0, x1, y0, y1 = x0 * 1.01, x1 * 1.01, y0 * 1.01, y1 * 1.01
    for _ in range(3000):
        ys = np.linspace(y0, y1, height)
        xs = np.linspace(x0, x1, width)
        bad_l = not _valid_in_input(model, np.stack([np.full(height, x0), ys], 1)).all()
        bad_r = not _valid_in_input(model, np.stack([np.full(height, x1), ys], 1)).all()
        bad_t = not _valid_in_input(model, np.stack([xs, np.full(width, y0)], 1)).all()
        bad_b = not _valid_in_input(model, np.stack([xs, np.full(width, y1)], 1)).all()
        if not (bad_l or bad_r or bad_t or bad_b):
            break
        if (bad_l or bad_r) and (bad_t or bad_b):
            if (x1 - x0) > (y1 - y0):
                bad_t = bad_b = False
            else:
                bad_l = bad_r = False
        if bad_l:
            x0 *= 0.995
        if bad_r:
            x1 *= 0.995
        if bad_t:
            y0 *= 0.995
        if bad_b:
            y1 *= 0.995
    else:
        raise CalibrationError(f"crop: no valid rectangle found for {model.describe()} (is the calibration right?)")
    fx = (width - 1.0) / (x1 - x0)
    fy = (height - 1.0) / (y1 - y0)
    return PinholeCamera(fx, fy, -x0 * fx, -y0 * fy, width, height)


def full_output_camera(model: CameraModel, width: int, height: int) -> PinholeCamera:
    """The pinhole camera of size ``width x height`` that sees the whole input image: the bounding box of the
    undistorted input border maps onto output pixels 0..W-1, 0..H-1 (black corners where the input has none)."""
    W, H = model.width, model.height
    us = np.arange(W, dtype=np.float64)
    vs = np.arange(H, dtype=np.float64)
    border = np.concatenate([np.stack([us, np.zeros(W)], 1), np.stack([us, np.full(W, H - 1.0)], 1),
                             np.stack([np.zeros(H), vs], 1), np.stack([np.full(H, W - 1.0), vs], 1)])
    xn, ok = model.normalized_from_pixel(border)
    if not ok.all():
        bad = border[~ok][0]
        raise CalibrationError(f"full: input pixel ({bad[0]:.0f}, {bad[1]:.0f}) of the {model.model_name} camera "
                               "cannot be undistorted onto a pinhole image plane (field of view too wide or the "
                               "distortion folds back); use crop or explicit output intrinsics")
    x0, y0 = xn.min(axis=0)
    x1, y1 = xn.max(axis=0)
    fx = (width - 1.0) / (x1 - x0)
    fy = (height - 1.0) / (y1 - y0)
    return PinholeCamera(fx, fy, -x0 * fx, -y0 * fy, width, height)


def _source_inside(model: CameraModel, xn: np.ndarray) -> np.ndarray:
    """Normalised points whose input pixel lies in ``[0, W-1] x [0, H-1]`` (the bilinear source is inside the
    input; the definition of :attr:`Undistorter.valid_mask`)."""
    uv, ok = model.pixel_from_normalized(xn)
    return ok & (uv[:, 0] >= 0) & (uv[:, 0] <= model.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= model.height - 1)


def keep_output_camera(model: CameraModel, width: int, height: int, border: int = KEEP_BORDER_PX) -> PinholeCamera:
    """The pinhole camera of size ``width x height`` that keeps the input's field of view: the ``full`` box (the
    whole input visible), each side pulled in by 0.2 % a step while the rectangle ``border`` pixels inside the output
    image still has a pixel without a source in the input. Pixels without a source then only lie in the outer
    ``border`` rows and columns (:data:`KEEP_BORDER_PX`), where the odometry never selects nor differentiates.

    Unlike :func:`crop_output_camera` (DSO's search) no side is shrunk for the sake of another: DSO's rule "when
    both dimensions have offenders, shrink only the wider one" zooms a pincushion lens such as TUM freiburg1's
    1.37x horizontally (docs/datasets.md). Raises :class:`CalibrationError` where ``full`` is impossible (a view
    beyond 90 degrees off axis) or no such rectangle exists.
    """
    full = full_output_camera(model, width, height)
    W, H = int(width), int(height)
    b = int(border)
    if not (0 <= b and 2 * b < min(W, H) - 1):
        raise CalibrationError(f"keep: border {border} px does not fit a {W}x{H} image")
    x0, x1 = -full.cx / full.fx, (W - 1.0 - full.cx) / full.fx
    y0, y1 = -full.cy / full.fy, (H - 1.0 - full.cy) / full.fy
    if not (x0 < 0 < x1 and y0 < 0 < y1):
        raise CalibrationError(f"keep: the principal point of {model.model_name} camera {model.describe()} is "
                               "not inside the image")
    cols = np.arange(b, W - b, dtype=np.float64)
    rows = np.arange(b, H - b, dtype=np.float64)
    for _ in range(5000):
        sx, sy = (x1 - x0) / (W - 1.0), (y1 - y0) / (H - 1.0)  # normalised units per output pixel
        xs, ys = x0 + cols * sx, y0 + rows * sy
        xl, xr, yt, yb = x0 + b * sx, x0 + (W - 1 - b) * sx, y0 + b * sy, y0 + (H - 1 - b) * sy
        bad_l = not _source_inside(model, np.stack([np.full(len(ys), xl), ys], 1)).all()
        bad_r = not _source_inside(model, np.stack([np.full(len(ys), xr), ys], 1)).all()
        bad_t = not _source_inside(model, np.stack([xs, np.full(len(xs), yt)], 1)).all()
        bad_b = not _source_inside(model, np.stack([xs, np.full(len(xs), yb)], 1)).all()
        if not (bad_l or bad_r or bad_t or bad_b):
            break
        if bad_l:
            x0 *= 0.998
        if bad_r:
            x1 *= 0.998
        if bad_t:
            y0 *= 0.998
        if bad_b:
            y1 *= 0.998
    else:
        raise CalibrationError(f"keep: no rectangle {b} px inside the image sees only the input for "
                               f"{model.describe()}")
    fx = (W - 1.0) / (x1 - x0)
    fy = (H - 1.0) / (y1 - y0)
    return PinholeCamera(fx, fy, -x0 * fx, -y0 * fy, W, H)


def output_camera_and_mode(model: CameraModel, output: Union[str, OutputSpec, PinholeCamera] = "none",
                           size: tuple[int, int] | None = None) -> tuple[PinholeCamera, str]:
    """:func:`make_output_camera` and the mode it used: ``keep`` falls back to ``crop`` (with a warning) for a lens
    whose whole view does not fit a pinhole image (beyond 90 degrees off axis)."""
    mode = output if isinstance(output, str) else (
        "explicit" if isinstance(output, PinholeCamera) else output.mode)
    try:
        return make_output_camera(model, output, size), mode
    except CalibrationError as exc:
        if mode != "keep":
            raise
        log.warning("rectify keep impossible (%s); using crop", exc)
        spec = output if isinstance(output, OutputSpec) else OutputSpec(mode="keep")
        return make_output_camera(model, dataclasses.replace(spec, mode="crop"), size), "crop"


def make_output_camera(model: CameraModel, output: Union[str, OutputSpec, PinholeCamera] = "none",
                       size: tuple[int, int] | None = None) -> PinholeCamera:
    """The undistorted pinhole camera for ``model``.

    ``output``: ``keep`` / ``crop`` / ``full`` / ``none``, an :class:`OutputSpec`, or a :class:`PinholeCamera` (used
    as is).
    ``size``: output ``(width, height)``; ``None`` = the spec's size, else the input size. A lens without
    distortion gets the input intrinsics scaled to the output size whatever the mode (so that it is passed through
    untouched at the same size).
    """
    if isinstance(output, PinholeCamera):
        if size is not None and tuple(size) != output.size:
            return output.resized(*size)
        return output
    spec = output if isinstance(output, OutputSpec) else OutputSpec(mode=str(output))
    w, h = tuple(size) if size is not None else (spec.size or model.size)
    if w <= 0 or h <= 0:
        raise CalibrationError(f"output size must be positive, got {w} x {h}")
    if spec.mode == "explicit":
        fx, fy, cx, cy = spec.intrinsics
        if spec.relative:
            return PinholeCamera(fx * w, fy * h, cx * w - 0.5, cy * h - 0.5, w, h)
        cam = PinholeCamera(fx, fy, cx, cy, *(spec.size or (w, h)))
        return cam if cam.size == (w, h) else cam.resized(w, h)
    if spec.mode == "none" or not model.has_distortion:
        return model.pinhole().resized(w, h) if (w, h) != model.size else model.pinhole()
    if spec.mode == "crop":
        return crop_output_camera(model, w, h)
    if spec.mode == "keep":
        return keep_output_camera(model, w, h)
    return full_output_camera(model, w, h)


# ================================================================================================= undistortion
class Undistorter:
    """Maps input images (model's geometry) to the output pinhole camera; remap tables are built once.

    ``kind``: ``passthrough`` (no distortion, same camera: the input array is returned as is), ``resize`` (no
    distortion, scaled camera: ``cv2.resize``), or ``remap`` (``cv2.remap`` with float32 tables; bilinear).

    ``valid_mask`` (bool ``[H_out, W_out]``, read-only) is False at the output pixels that have no source: their
    ray, through the lens model in float64, lands outside ``[0, W_in - 1] x [0, H_in - 1]`` or outside the model's
    invertible region. :meth:`apply` fills them with the nearest input pixel (edge replicate), not black, so that
    they make no artificial edge for gradient-based pixel selection; :meth:`apply_nearest` (depth, labels) leaves
    them 0. ``invalid_pixels`` counts them.
    """

    def __init__(self, input_camera: CameraModel, output_camera: PinholeCamera):
        self.input = input_camera
        self.output = output_camera
        self.map_x: np.ndarray | None = None  # [H_out, W_out] float32 input x of each output pixel (-16: outside)
        self.map_y: np.ndarray | None = None
        same_k = (input_camera.fx, input_camera.fy, input_camera.cx, input_camera.cy) == (
            output_camera.fx, output_camera.fy, output_camera.cx, output_camera.cy)
        if not input_camera.has_distortion and input_camera.size == output_camera.size and same_k:
            self.kind = "passthrough"
        elif not input_camera.has_distortion and _is_pure_resize(input_camera, output_camera):
            self.kind = "resize"
        else:
            self.kind = "remap"
            self.map_x, self.map_y = self._build_maps()
        if self.kind == "remap":
            self.valid_mask = self._source_mask()
        else:
            self.valid_mask = np.ones((output_camera.height, output_camera.width), dtype=bool)
        self.valid_mask.setflags(write=False)  # shared by every frame
        self.invalid_pixels = int(self.valid_mask.size - np.count_nonzero(self.valid_mask))

    def _source_mask(self) -> np.ndarray:
        out = self.output
        uu, vv = np.meshgrid(np.arange(out.width, dtype=np.float64), np.arange(out.height, dtype=np.float64))
        xn = np.stack([(uu.ravel() - out.cx) / out.fx, (vv.ravel() - out.cy) / out.fy], axis=1)
        return _source_inside(self.input, xn).reshape(out.height, out.width)

    @property
    def valid_fraction(self) -> float:
        """Share of the output pixels that have a source in the input."""
        return 1.0 - self.invalid_pixels / self.valid_mask.size

    @property
    def passthrough(self) -> bool:
        return self.kind == "passthrough"

    def _build_maps(self) -> tuple[np.ndarray, np.ndarray]:
        inp, out = self.input, self.output
        size = out.size
        if isinstance(inp, RadTanCamera) or (isinstance(inp, PinholeCamera)):
            dist = inp.dist_coeffs if isinstance(inp, RadTanCamera) else np.zeros(5)
            mx, my = cv2.initUndistortRectifyMap(inp.K, dist, np.eye(3), out.K, size, cv2.CV_32FC1)
        elif isinstance(inp, EquidistantCamera):
            mx, my = cv2.fisheye.initUndistortRectifyMap(inp.K, inp.dist_coeffs.reshape(4, 1), np.eye(3), out.K,
                                                         size, cv2.CV_32FC1)
        else:
            uu, vv = np.meshgrid(np.arange(out.width, dtype=np.float64), np.arange(out.height, dtype=np.float64))
            xn = np.stack([(uu.ravel() - out.cx) / out.fx, (vv.ravel() - out.cy) / out.fy], axis=1)
            uv, _ = inp.pixel_from_normalized(xn)
            mx = uv[:, 0].reshape(out.height, out.width).astype(np.float32)
            my = uv[:, 1].reshape(out.height, out.width).astype(np.float32)
        # Outside the model's invertible region the tables are meaningless (a folding polynomial maps far-out rays
        # back into the image): mark them outside, as DSO marks out-of-image sources.
        if math.isfinite(inp.max_radius):
            uu, vv = np.meshgrid(np.arange(out.width, dtype=np.float64), np.arange(out.height, dtype=np.float64))
            r = np.hypot((uu - out.cx) / out.fx, (vv - out.cy) / out.fy)
            bad = r >= inp.max_radius
            mx[bad] = -16.0
            my[bad] = -16.0
        bad = ~(np.isfinite(mx) & np.isfinite(my))
        mx[bad] = -16.0
        my[bad] = -16.0
        return np.ascontiguousarray(mx, dtype=np.float32), np.ascontiguousarray(my, dtype=np.float32)

    def apply(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR, *, fill_edge: bool = True) -> np.ndarray:
        """Undistort an image ``[H_in, W_in(, C)]`` of any dtype OpenCV remaps (uint8, uint16, float32).

        Output pixels without a source (``~valid_mask``) hold the nearest input pixel (``fill_edge``) or 0."""
        if image.shape[:2] != (self.input.height, self.input.width):
            raise ValueError(f"image of size {image.shape[1]}x{image.shape[0]} given to an undistorter for "
                             f"{self.input.width}x{self.input.height}")
        if self.kind == "passthrough":
            return image
        if self.kind == "resize":
            shrink = self.output.width < self.input.width and self.output.height < self.input.height
            interp = interpolation
            if interpolation == cv2.INTER_LINEAR and shrink:
                interp = cv2.INTER_AREA
            return cv2.resize(image, self.output.size, interpolation=interp)
        if not fill_edge or not self.invalid_pixels:
            return cv2.remap(image, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0)
        return cv2.remap(image, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)

    def apply_nearest(self, image: np.ndarray) -> np.ndarray:
        """Undistort with nearest-neighbour sampling (depth maps, masks, labels: no mixing of values); pixels
        without a source are 0."""
        out = self.apply(image, interpolation=cv2.INTER_NEAREST, fill_edge=False)
        if self.invalid_pixels:
            out = out.copy() if out is image else out
            out[~self.valid_mask] = 0
        return out

    def source_pixels(self, uv_out) -> np.ndarray:
        """Input-image pixel ``(N, 2)`` that each output pixel ``(N, 2)`` samples (NaN where outside the model)."""
        uv_out = _as_points(uv_out, 2, "source_pixels")
        xn = np.stack([(uv_out[:, 0] - self.output.cx) / self.output.fx,
                       (uv_out[:, 1] - self.output.cy) / self.output.fy], axis=1)
        uv, ok = self.input.pixel_from_normalized(xn)
        uv[~ok] = np.nan
        return uv


def _is_pure_resize(inp: CameraModel, out: PinholeCamera) -> bool:
    expect = inp.pinhole().resized(out.width, out.height)
    return all(abs(a - b) <= 1e-9 * max(1.0, abs(a)) for a, b in zip(
        (expect.fx, expect.fy, expect.cx, expect.cy), (out.fx, out.fy, out.cx, out.cy)))


# ========================================================================================= photometric calibration
def read_inverse_response(path: str | Path) -> np.ndarray:
    """TUM monoVO ``pcalib.txt``: the inverse response ``G^-1`` as one line of at least 256 strictly increasing
    numbers (one per raw value). Returned rescaled to ``[0, 255]`` (DSO does the same), float32."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: photometric response file not found")
    text = path.read_text(encoding="utf-8", errors="replace").strip()
    if not text:
        raise CalibrationError(f"{path}: empty photometric response file (expected 256 numbers on the first line)")
    first = text.splitlines()[0]
    try:
        g = np.array([float(v) for v in first.split()], dtype=np.float64)
    except ValueError:
        raise CalibrationError(f"{path}: the inverse response must be numbers, got {first[:80]!r}") from None
    if len(g) < 256:
        raise CalibrationError(f"{path}: expected at least 256 values of G^-1 on the first line, got {len(g)}")
    if not np.all(np.isfinite(g)):
        raise CalibrationError(f"{path}: non-finite value in the inverse response")
    bad = np.nonzero(np.diff(g) <= 0)[0]
    if len(bad):
        i = int(bad[0])
        raise CalibrationError(f"{path}: the inverse response must be strictly increasing, but value {i + 1} "
                               f"({g[i + 1]}) <= value {i} ({g[i]})")
    return (255.0 * (g - g[0]) / (g[-1] - g[0])).astype(np.float32)


def read_vignette(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """TUM monoVO ``vignette.png`` (8 or 16 bit gray) -> float32 ``[H, W]`` attenuation normalised to max 1.

    ``size`` ``(width, height)``, when given, must match the image size."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: vignette image not found")
    img = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CalibrationError(f"{path}: not a readable image (expected an 8- or 16-bit gray PNG)")
    if img.ndim == 3:
        if img.shape[2] >= 3 and not (np.array_equal(img[..., 0], img[..., 1])
                                      and np.array_equal(img[..., 0], img[..., 2])):
            raise CalibrationError(f"{path}: vignette must be a gray image, got {img.shape[2]} different channels")
        img = img[..., 0]
    if img.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(f"{path}: vignette must be 8 or 16 bit, got {img.dtype}")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise CalibrationError(f"{path}: vignette is {img.shape[1]}x{img.shape[0]} but the images are "
                               f"{size[0]}x{size[1]}")
    v = img.astype(np.float32)
    m = float(v.max())
    if m <= 0:
        raise CalibrationError(f"{path}: vignette image is all zero")
    return v / m


class PhotometricCalibration:
    """Inverse camera response ``G^-1`` and vignette ``V`` (both optional; absent = identity).

    :meth:`apply` gives DSO's irradiance ``G^-1(I_raw) / V(x)`` on a 0-255 scale, in the *input* geometry (apply it
    before undistortion; the vignette is never remapped). Pixels where ``V == 0`` become 0.
    """

    def __init__(self, inverse_response: np.ndarray | None = None, vignette: np.ndarray | None = None,
                 response_source: str = "", vignette_source: str = ""):
        self.inverse_response = None if inverse_response is None else np.asarray(inverse_response, np.float32)
        self.vignette = None if vignette is None else np.asarray(vignette, np.float32)
        self.response_source = response_source
        self.vignette_source = vignette_source
        self._inv_vignette = None
        if self.vignette is not None:
            with np.errstate(divide="ignore"):
                self._inv_vignette = np.where(self.vignette > 0, 1.0 / self.vignette, 0.0).astype(np.float32)

    @classmethod
    def identity(cls) -> "PhotometricCalibration":
        return cls()

    @classmethod
    def from_files(cls, pcalib: str | Path | None = None, vignette: str | Path | None = None,
                   image_size: tuple[int, int] | None = None) -> "PhotometricCalibration":
        """Read ``pcalib.txt`` and/or ``vignette.png`` (either may be ``None``)."""
        g = read_inverse_response(pcalib) if pcalib is not None else None
        v = read_vignette(vignette, image_size) if vignette is not None else None
        return cls(g, v, str(pcalib or ""), str(vignette or ""))

    @property
    def is_identity(self) -> bool:
        return self.inverse_response is None and self.vignette is None

    def apply(self, image: np.ndarray, exposure_ms: float | None = None, *,
              normalize_exposure: bool = False) -> np.ndarray:
        """Raw gray image ``[H, W]`` (uint8, or uint16 when the response has 65536 entries; other inputs are used
        as values) -> float32 irradiance ``G^-1(raw) / V`` (0-255 scale).

        ``exposure_ms`` is not used by DSO's model here (the tracker takes exposure into its affine brightness);
        with ``normalize_exposure=True`` the result is divided by it (radiance per millisecond), which requires a
        positive exposure.
        """
        if image.ndim != 2:
            raise ValueError(f"photometric correction needs a gray image, got shape {image.shape}")
        g = self.inverse_response
        if g is None:
            out = image.astype(np.float32)
        elif image.dtype == np.uint8 and len(g) == 256:
            out = cv2.LUT(image, g.reshape(1, 256)).astype(np.float32, copy=False)
        elif np.issubdtype(image.dtype, np.integer):
            if int(image.max(initial=0)) >= len(g):
                raise ValueError(f"raw value {int(image.max())} beyond the inverse response's {len(g)} entries")
            out = np.take(g, image)
        else:
            idx = np.clip(image, 0, len(g) - 1)
            out = np.interp(idx, np.arange(len(g)), g).astype(np.float32)
        if self._inv_vignette is not None:
            if self._inv_vignette.shape != image.shape:
                raise ValueError(f"image {image.shape[1]}x{image.shape[0]} does not match the vignette "
                                 f"{self._inv_vignette.shape[1]}x{self._inv_vignette.shape[0]}")
            out = out * self._inv_vignette
        if normalize_exposure:
            if exposure_ms is None or not exposure_ms > 0:
                raise ValueError(f"normalize_exposure needs a positive exposure time, got {exposure_ms if exposure_ms is None else float(exposure_ms)}")
            out = out / np.float32(exposure_ms)
        return out.astype(np.float32, copy=False)

    def describe(self) -> dict:
        return {"response": self.inverse_response is not None, "vignette": self.vignette is not None,
                "response_file": self.response_source or None, "vignette_file": self.vignette_source or None}


# ================================================================================================ calibration
@dataclass(frozen=True)
class CameraSpec:
    """A parsed calibration file: the lens model (input camera) and what it asks of the output."""

    model: CameraModel
    output: OutputSpec = OutputSpec()
    source: str = ""


class Calibration:
    """Input camera model + output pinhole camera + undistorter + photometric calibration.

    Per frame: :meth:`gray_from_raw` (photometric correction in the input geometry, then undistortion) and
    :meth:`rgb_from_raw` (undistortion only; see the method).
    """

    def __init__(self, input_camera: CameraModel, output_camera: PinholeCamera,
                 photometric: PhotometricCalibration | None = None, output_mode: str = "none", source: str = ""):
        self.input = input_camera
        self.output = output_camera
        self.photometric = photometric if photometric is not None else PhotometricCalibration.identity()
        if self.photometric.vignette is not None and self.photometric.vignette.shape != (
                input_camera.height, input_camera.width):
            v = self.photometric.vignette
            raise CalibrationError(f"{self.photometric.vignette_source or 'vignette'}: vignette is "
                                   f"{v.shape[1]}x{v.shape[0]} but the camera is {input_camera.width}x"
                                   f"{input_camera.height}")
        self.output_mode = output_mode
        self.source = source
        self.undistorter = Undistorter(input_camera, output_camera)

    @classmethod
    def create(cls, model: CameraModel, output: Union[str, OutputSpec, PinholeCamera] = "none",
               size: tuple[int, int] | None = None, photometric: PhotometricCalibration | None = None,
               source: str = "") -> "Calibration":
        """Build from a lens model and an output choice (see :func:`make_output_camera`; ``keep`` falls back to
        ``crop`` where the lens sees beyond 90 degrees, see :func:`output_camera_and_mode`)."""
        camera, mode = output_camera_and_mode(model, output, size)
        return cls(model, camera, photometric, mode, source)

    @classmethod
    def from_spec(cls, spec: CameraSpec, *, rectify: str | None = None, size: tuple[int, int] | None = None,
                  photometric: PhotometricCalibration | None = None) -> "Calibration":
        """Build from a parsed file; ``rectify`` (crop/full/none) and ``size`` override what the file says."""
        out = spec.output
        if rectify:
            if rectify not in RECTIFY_MODES:
                raise CalibrationError(f"rectify must be one of {RECTIFY_MODES}, got {rectify!r}")
            out = OutputSpec(mode=rectify, size=out.size)
        try:
            return cls.create(spec.model, out, size, photometric, spec.source)
        except CalibrationError as exc:
            raise CalibrationError(f"{spec.source}: {exc}" if spec.source else str(exc)) from None

    @property
    def input_size(self) -> tuple[int, int]:
        return self.input.size

    @property
    def valid_mask(self) -> np.ndarray | None:
        """bool ``[H_out, W_out]`` (read-only, shared): False where an output pixel has no source in the input;
        ``None`` when every pixel has one. What :attr:`mgso.io.Frame.valid` carries."""
        u = self.undistorter
        return u.valid_mask if u.invalid_pixels else None

    @property
    def output_size(self) -> tuple[int, int]:
        return self.output.size

    def gray_from_raw(self, raw_gray: np.ndarray, photometric: bool = True) -> np.ndarray:
        """Raw gray ``[H_in, W_in]`` -> float32 ``[H_out, W_out]`` on the 0-255 scale: photometric correction (when
        present and ``photometric``) in the input geometry, then undistortion."""
        if photometric and not self.photometric.is_identity:
            img = self.photometric.apply(raw_gray)
        elif raw_gray.dtype == np.uint16:
            img = raw_gray.astype(np.float32) * np.float32(255.0 / 65535.0)
        else:
            img = raw_gray.astype(np.float32)
        return self.undistorter.apply(img)  # img is always a fresh float32 array, never the caller's

    def rgb_from_raw(self, raw: np.ndarray) -> np.ndarray:
        """Raw image (gray ``[H, W]`` or OpenCV BGR ``[H, W, 3]``, uint8/uint16) -> undistorted RGB float32
        ``[H_out, W_out, 3]`` in [0, 1]. No photometric correction: colours are what the camera recorded (the
        vignette division can exceed the [0, 1] range); gray input is replicated into three channels."""
        scale = np.float32(1.0 / 65535.0) if raw.dtype == np.uint16 else np.float32(1.0 / 255.0)
        code = cv2.COLOR_GRAY2RGB if raw.ndim == 2 else cv2.COLOR_BGR2RGB
        rgb = cv2.cvtColor(self.undistorter.apply(raw if raw.ndim == 2 else raw[:, :, :3]), code)
        out = rgb.astype(np.float32)
        out *= scale  # in place: one pass fewer over a large image
        return out

    def describe(self) -> dict:
        return {"input": self.input.describe(), "output": self.output.describe(), "output_mode": self.output_mode,
                "undistortion": self.undistorter.kind, "valid_fraction": self.undistorter.valid_fraction,
                "photometric": self.photometric.describe(),
                "source": self.source or None}
