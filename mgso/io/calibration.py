"""Calibration files that belong to no one dataset, and the reader that recognises any calibration file.

- :func:`read_camera_file`: any supported file, recognised by its content (DSO ``camera.txt``, EuRoC ``sensor.yaml``,
  KITTI ``calib.txt``, Replica ``cam_params.json``, plain intrinsics); the dataset formats' readers live beside their
  dataset readers (:func:`mgso.io.euroc.read_euroc_sensor_yaml`, :func:`mgso.io.kitti.read_kitti_calib`,
  :func:`mgso.io.replica.read_replica_cam_params`, :func:`mgso.io.tum.tum_rgbd_default`), which register them
  (:func:`register_calibration_format`): this module imports no dataset reader.
- :func:`read_dso_camera_txt`, :func:`read_plain_intrinsics`: the generic formats.
- :func:`load_calibration`: a file (and photometric files) straight to a :class:`~mgso.camera.Calibration`.

Camera models, output cameras, undistortion and photometric calibration are :mod:`mgso.camera`'s (which never
imports :mod:`mgso.io`). Errors are :class:`~mgso.camera.CalibrationError` naming the file (and line).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..camera import (RECTIFY_MODES, Calibration, CalibrationError, CameraModel, CameraSpec, EquidistantCamera,
                      FOVCamera, OutputSpec, PhotometricCalibration, PinholeCamera, RadTanCamera)

__all__ = ["read_camera_file", "read_dso_camera_txt", "read_plain_intrinsics", "plain_intrinsics", "inline_intrinsics",
           "load_calibration", "numbers", "abs_intrinsics", "CalibrationFormat", "register_calibration_format"]


def numbers(line: str) -> list[float] | None:
    try:
        return [float(v) for v in line.replace(",", " ").split()]
    except ValueError:
        return None


def abs_intrinsics(p: list[float], w: int, h: int) -> list[float]:
    """DSO's rule: intrinsics with ``cx < 1 and cy < 1`` are relative to the image size (pixel (0, 0) covering
    [0, 1]^2); convert them to pixels with pixel centres at integers."""
    if p[2] < 1 and p[3] < 1:
        return [p[0] * w, p[1] * h, p[2] * w - 0.5, p[3] * h - 0.5] + list(p[4:])
    return list(p)


_DSO_MODELS = {"pinhole": 5, "radtan": 8, "fov": 5, "equidistant": 8, "kannalabrandt": 8}


def _is_dso_camera_txt(lines: list[str]) -> bool:
    if not lines:
        return False
    first = lines[0].split()
    if first and first[0].lower() in _DSO_MODELS:
        return True
    nums = numbers(lines[0])
    if nums is None or len(nums) not in (5, 8) or len(lines) < 2:
        return False
    size = numbers(lines[1])
    return size is not None and len(size) == 2


def read_dso_camera_txt(path: str | Path) -> CameraSpec:
    """DSO's ``camera.txt``.

    Line 1: ``Pinhole fx fy cx cy 0`` | ``RadTan fx fy cx cy k1 k2 p1 p2 [k3]`` (k3: our extension) |
    ``EquiDistant fx fy cx cy k1 k2 k3 k4`` | ``KannalaBrandt fx fy cx cy k1 k2 k3 k4`` |
    ``FOV fx fy cx cy omega``, or without a name the legacy forms
    (5 numbers: ATAN/FOV, a pinhole when omega is 0; 8 numbers: RadTan). Intrinsics relative to the image size when
    ``cx < 1 and cy < 1`` (converted with the 0.5-pixel shift), else pixels.
    Line 2: input ``width height``. Line 3: ``crop`` | ``full`` | ``none`` | ``keep`` (ours) | ``fx fy cx cy 0`` (relative when
    ``cx, cy < 1``, as DSO expects, else pixels). Line 4: output ``width height``. Lines 3-4 may be absent (then
    ``none`` at the input size); line 4 absent means the input size.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: camera calibration file not found")
    lines = [ln.strip() for ln in path.read_text(encoding="utf-8", errors="replace").splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if len(lines) < 2:
        raise CalibrationError(f"{path}: a DSO camera.txt needs at least 2 lines (model and parameters; input width "
                               f"height), got {len(lines)}")
    parts = lines[0].split()
    name = parts[0].lower() if parts and parts[0].lower() in _DSO_MODELS else None
    vals = numbers(" ".join(parts[1:] if name else parts))
    if vals is None:
        raise CalibrationError(f"{path}:1: expected a model name and numbers, got {lines[0][:80]!r}")
    if name is None:
        if len(vals) == 8:
            name = "radtan"
        elif len(vals) == 5:
            name = "pinhole" if vals[4] == 0 else "fov"
        else:
            raise CalibrationError(f"{path}:1: expected 5 (fx fy cx cy omega) or 8 (fx fy cx cy k1 k2 p1 p2) "
                                   f"numbers, got {len(vals)}")
    elif name == "pinhole" and len(vals) == 4:
        vals = vals + [0.0]
    if name == "radtan" and len(vals) == 9 and parts[0].lower() == "radtan":
        pass  # our extension: RadTan fx fy cx cy k1 k2 p1 p2 k3 (OpenCV's 5-coefficient model)
    elif len(vals) != _DSO_MODELS[name]:
        raise CalibrationError(f"{path}:1: {parts[0]} takes {_DSO_MODELS[name]} numbers, got {len(vals)}")
    size = numbers(lines[1])
    if size is None or len(size) != 2 or not all(s > 0 and float(s).is_integer() for s in size):
        raise CalibrationError(f"{path}:2: expected the input image size 'width height', got {lines[1][:80]!r}")
    w, h = int(size[0]), int(size[1])
    p = abs_intrinsics(vals, w, h)
    try:
        if name == "pinhole":
            if p[4] != 0:
                raise CalibrationError(f"{path}:1: Pinhole takes a 0 as fifth number, got {p[4]}")
            model: CameraModel = PinholeCamera(p[0], p[1], p[2], p[3], w, h)
        elif name == "fov":
            model = FOVCamera(p[0], p[1], p[2], p[3], w, h, omega=p[4])
        elif name == "radtan":
            model = RadTanCamera(p[0], p[1], p[2], p[3], w, h, *p[4:])
        else:
            model = EquidistantCamera(p[0], p[1], p[2], p[3], w, h, p[4], p[5], p[6], p[7])
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    out_size = None
    if len(lines) >= 4:
        osz = numbers(lines[3])
        if osz is None or len(osz) != 2 or not all(s > 0 and float(s).is_integer() for s in osz):
            raise CalibrationError(f"{path}:4: expected the output image size 'width height', got {lines[3][:80]!r}")
        out_size = (int(osz[0]), int(osz[1]))
    if len(lines) >= 3:
        l3 = lines[2].strip()
        if l3.lower() in RECTIFY_MODES:
            output = OutputSpec(mode=l3.lower(), size=out_size)
        else:
            o = numbers(l3)
            if o is None or len(o) not in (4, 5):
                raise CalibrationError(f"{path}:3: expected keep, crop, full, none or 'fx fy cx cy 0', got {l3[:80]!r}")
            if len(o) == 5 and o[4] != 0:
                raise CalibrationError(f"{path}:3: the output camera is a pinhole; its fifth number must be 0, got "
                                       f"{o[4]}")
            relative = o[2] < 1 and o[3] < 1
            output = OutputSpec(mode="explicit", size=out_size, intrinsics=tuple(o[:4]), relative=relative)
    else:
        output = OutputSpec(mode="none", size=out_size)
    return CameraSpec(model, output, str(path))


def read_plain_intrinsics(path: str | Path, image_size: tuple[int, int] | None) -> CameraSpec:
    """A text file of ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` (whitespace or commas, any line breaks, ``#`` comments).

    The file holds no image size, so ``image_size`` ``(width, height)`` (from the images) is required. Distorted
    models are rectified with ``keep``.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found")
    text = " ".join(ln.split("#")[0] for ln in path.read_text(encoding="utf-8", errors="replace").splitlines())
    return plain_intrinsics(text, str(path), image_size)


def plain_intrinsics(text: str, source: str, image_size: tuple[int, int] | None) -> CameraSpec:
    """``fx fy cx cy [k1 k2 p1 p2 [k3]]`` given as text (a plain intrinsics file's content, or the numbers
    themselves: ``mgso run VIDEO --calib "525 525 319.5 239.5"``); errors name ``source``."""
    vals = numbers(text)
    if vals is None:
        raise CalibrationError(f"{source}: expected numbers 'fx fy cx cy [k1 k2 p1 p2 [k3]]', got "
                               f"{text.strip()[:80]!r}")
    if len(vals) not in (4, 8, 9):
        raise CalibrationError(f"{source}: expected 4 (fx fy cx cy), 8 (+ k1 k2 p1 p2) or 9 (+ k3) numbers, got "
                               f"{len(vals)}")
    if image_size is None:
        raise CalibrationError(f"{source}: plain intrinsics hold no image size; it is needed from the images")
    w, h = image_size
    p = abs_intrinsics(vals, w, h)
    try:
        if len(p) == 4:
            model: CameraModel = PinholeCamera(p[0], p[1], p[2], p[3], w, h)
        else:
            model = RadTanCamera(p[0], p[1], p[2], p[3], w, h, *p[4:])
    except CalibrationError as exc:
        raise CalibrationError(f"{source}: {exc}") from None
    return CameraSpec(model, OutputSpec(mode="keep" if model.has_distortion else "none"), source)


def inline_intrinsics(text: str) -> bool:
    """Whether a calibration argument is the intrinsics themselves rather than a file: numbers only (how many is
    :func:`plain_intrinsics`' to judge) and no file of that name."""
    vals = numbers(str(text))
    return bool(vals) and not Path(str(text)).exists()


@dataclass(frozen=True)
class CalibrationFormat:
    """A dataset's own calibration file format, which :func:`read_camera_file` recognises by its content:
    ``recognises(path, text, lines)`` (``lines``: the non-empty lines that are not ``#`` comments) and
    ``read(path, image_size)`` to a :class:`~mgso.camera.CameraSpec`. The dataset readers register theirs
    (:func:`register_calibration_format`) beside their own code, so this module imports none of them."""

    name: str
    recognises: Callable[[Path, str, list[str]], bool]
    read: Callable[[Path, "tuple[int, int] | None"], CameraSpec]


_FORMATS: list[CalibrationFormat] = []


def register_calibration_format(fmt: CalibrationFormat) -> CalibrationFormat:
    """Add a dataset's calibration format to those :func:`read_camera_file` tries (before DSO's ``camera.txt`` and
    plain intrinsics); a name registered again replaces the earlier one."""
    _FORMATS[:] = [f for f in _FORMATS if f.name != fmt.name] + [fmt]
    return fmt


def read_camera_file(path: str | Path, image_size: tuple[int, int] | None = None) -> CameraSpec:
    """Read any supported calibration file, recognised by its content: the dataset formats registered by their
    readers (EuRoC ``sensor.yaml``, KITTI ``calib.txt`` (``P0:``), Replica ``cam_params.json``), DSO
    ``camera.txt``, or a plain ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` file; or those 4, 8 or 9 numbers themselves in
    place of a path (:func:`inline_intrinsics`). ``image_size`` ``(width, height)`` is needed by formats that hold
    no size (KITTI, plain)."""
    if inline_intrinsics(str(path)):
        return plain_intrinsics(str(path), str(path).strip(), image_size)   # the numbers: a run's source, reusable
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found")
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    for fmt in _FORMATS:
        if fmt.recognises(path, text, lines):
            return fmt.read(path, image_size)
    if not lines:
        raise CalibrationError(f"{path}: empty calibration file")
    if _is_dso_camera_txt(lines):
        return read_dso_camera_txt(path)
    return read_plain_intrinsics(path, image_size)


def load_calibration(path: str | Path, image_size: tuple[int, int] | None = None, *, rectify: str | None = None,
                     size: tuple[int, int] | None = None, pcalib: str | Path | None = None,
                     vignette: str | Path | None = None) -> Calibration:
    """Read a calibration file (see :func:`read_camera_file`) and optional photometric files into a
    :class:`Calibration`. ``rectify`` / ``size`` override the file's output mode and size."""
    spec = read_camera_file(path, image_size)
    photo = PhotometricCalibration.from_files(pcalib, vignette, spec.model.size) if (pcalib or vignette) else None
    return Calibration.from_spec(spec, rectify=rectify, size=size, photometric=photo)
