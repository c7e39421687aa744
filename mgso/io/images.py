"""Image decoding with clear errors, image listings, small text-table readers shared by the dataset readers."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np

from .errors import DatasetError

log = logging.getLogger(__name__)

__all__ = ["IMAGE_EXTENSIONS", "VIDEO_EXTENSIONS", "decode_image", "read_image", "read_bytes", "is_jpeg",
           "list_images", "natural_key", "read_table", "parse_float", "check_increasing", "read_first_image"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts")


def _truncated_jpeg(buf: np.ndarray) -> bool:
    """A JPEG (starts with the SOI marker FF D8) whose data ends before the EOI marker FF D9 (trailing zero padding
    allowed): libjpeg decodes such a file into an image whose missing part is flat gray, with only a warning on
    stderr, which the odometry would track as a real frame."""
    if buf.size < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        return False
    end = buf.size
    while end > 2 and buf[end - 1] == 0:
        end -= 1
    return not (buf[end - 2] == 0xFF and buf[end - 1] == 0xD9)


def is_jpeg(data: np.ndarray) -> bool:
    """Encoded bytes that start with JPEG's start-of-image marker (FF D8)."""
    return data.size >= 2 and data[0] == 0xFF and data[1] == 0xD8


def decode_image(data: bytes | np.ndarray, source: str, gray: bool = False) -> np.ndarray:
    """Decode encoded image bytes as stored (8/16 bit, gray or BGR; an alpha channel is dropped).

    ``gray``: a JPEG is decoded straight to its luma plane (``IMREAD_GRAYSCALE``: libjpeg skips the chroma, 0.74-1.0
    ms against 1.6-1.7 ms for colour and a conversion at 640x480, 2026-12-04), as the reference DSO reads its images;
    other formats are decoded as stored and left to the caller's conversion."""
    buf = np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    if buf.size == 0:
        raise DatasetError(f"{source}: empty image file")
    if _truncated_jpeg(buf):
        raise DatasetError(f"{source}: truncated JPEG (the file ends before its end-of-image marker)")
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE if gray and is_jpeg(buf) else cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{source}: not a readable image (corrupt or unsupported format)")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        elif img.shape[2] == 1:
            img = img[:, :, 0]
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{source}: unsupported pixel type {img.dtype} (expected 8- or 16-bit images)")
    return img


def read_bytes(path: str | Path) -> np.ndarray:
    """An image file's encoded bytes (uint8); a missing or unreadable file is a :class:`DatasetError`."""
    path = Path(path)
    try:
        return np.fromfile(str(path), dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read image file: {exc}") from None


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file (see :func:`decode_image`); a missing or corrupt file is a :class:`DatasetError`."""
    return decode_image(read_bytes(path), str(path))


def read_first_image(files: list[Path], limit: int = 10) -> tuple[np.ndarray, Path]:
    """The first of ``files`` that can be read (what a sequence takes its image size and colour from) and its path.
    An unreadable first frame is skipped as the same fault later in the sequence is (its row in frames.csv says so
    when the run reaches it), with a warning; only when none of the first ``limit`` can be read is the sequence
    refused, naming the first's problem."""
    errors = []
    for path in files[:limit]:
        try:
            img = read_image(path)
        except DatasetError as exc:
            errors.append(str(exc))
            continue
        if errors:
            log.warning("%s; the image size is taken from %s", "; ".join(errors), Path(path).name)
        return img, Path(path)
    if not files:
        raise DatasetError("no images")
    n = min(len(files), limit)
    raise DatasetError(f"{errors[0]} (and none of the first {n} images can be read)" if n > 1 else errors[0])


def natural_key(name: str):
    """Sort key that orders ``frame2`` before ``frame10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path, pattern: str | None = None) -> list[Path]:
    """Image files directly in ``folder`` (optionally matching a regex on the name), in natural order."""
    rx = re.compile(pattern) if pattern else None
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
             and (rx is None or rx.fullmatch(p.name))]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_table(path: Path, min_cols: int, what: str, comment: str = "#") -> list[tuple[int, list[str]]]:
    """Rows of a whitespace/comma separated text file as ``(line number, fields)``; comment and empty lines skipped.

    Every row must have at least ``min_cols`` fields."""
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for n, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith(comment):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) < min_cols:
                raise DatasetError(f"{path}:{n}: expected at least {min_cols} fields in {what}, got {s[:80]!r}")
            rows.append((n, parts))
    if not rows:
        raise DatasetError(f"{path}: {what} has no entries")
    return rows


def parse_float(value: str, path: Path, line: int, what: str) -> float:
    try:
        v = float(value)
    except ValueError:
        raise DatasetError(f"{path}:{line}: {what} is not a number: {value!r}") from None
    if not np.isfinite(v):
        raise DatasetError(f"{path}:{line}: {what} is not finite: {value!r}")
    return v


def check_increasing(timestamps: np.ndarray, source: str, lines: list[int] | None = None) -> None:
    """Timestamps must be strictly increasing; the error names the source and the first offending entry."""
    bad = np.nonzero(np.diff(timestamps) <= 0)[0]
    if len(bad):
        i = int(bad[0]) + 1
        where = f"{source}:{lines[i]}" if lines is not None else f"{source} (entry {i})"
        raise DatasetError(f"{where}: timestamps out of order ({float(timestamps[i])!r} after "
                           f"{float(timestamps[i - 1])!r})")
