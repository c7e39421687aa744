"""Helpers of the tracking tests: synthetic frames as mgso.io frames."""

from __future__ import annotations

import numpy as np

from mgso.io.sequence import Frame

GRAY = np.array([0.299, 0.587, 0.114], np.float32)


def gray_of(img: np.ndarray) -> np.ndarray:
    """[H, W, 3] in [0, 1] -> [H, W] float32 in 0-255 (what mgso.io gives the tracker)."""
    return (img @ GRAY) * np.float32(255.0)


def frames_of(seq, images=None, start: int = 0) -> list[Frame]:
    """mgso.io.Frame objects of a synthetic sequence (optionally with replaced images)."""
    imgs = seq.images if images is None else images
    return [Frame(start + i, float(seq.timestamps[0]) + (start + i) / seq.spec.fps, gray_of(imgs[i]), None,
                  rgb=imgs[i]) for i in range(len(imgs))]
