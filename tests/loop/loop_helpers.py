"""What the loop tests share: stand-ins for DSO's points on a rendered synthetic view."""

import cv2
import numpy as np


def dso_points(image, depth, n=2000, seed=0):
    """Stand-ins for DSO's points: ``n`` random pixels among the 20 % of highest gradient, with 1 / depth."""
    g = cv2.cvtColor((image * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    mag[:4], mag[-4:], mag[:, :4], mag[:, -4:] = 0, 0, 0, 0
    ys, xs = np.nonzero(mag > np.percentile(mag, 80))
    k = np.random.default_rng(seed).choice(len(xs), min(n, len(xs)), replace=False)
    return np.stack([xs[k], ys[k]], 1).astype(np.float64), 1.0 / depth[ys[k], xs[k]].astype(np.float64)
