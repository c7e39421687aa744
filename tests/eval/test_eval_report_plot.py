"""mgso.eval.report_plot: the one-page report drawn from values (the full run's report.png is tested in
tests/test_system.py)."""

from __future__ import annotations

import cv2
import numpy as np

from mgso.eval import PsnrSeries, ReportData, plot_report
from mgso.eval.report_plot import REPORT_DPI, REPORT_SIZE_INCHES


def _size():
    return round(REPORT_SIZE_INCHES[0] * REPORT_DPI), round(REPORT_SIZE_INCHES[1] * REPORT_DPI)


def test_an_empty_report_is_still_one_readable_page(tmp_path):
    """Nothing to draw (no pose, no evaluation, no map): every panel says why instead of failing."""
    path = plot_report(tmp_path / "r.png", ReportData(title="empty"))
    img = cv2.imread(str(path))
    assert img is not None and (img.shape[1], img.shape[0]) == _size()


def test_series_are_drawn_where_their_panels_are(tmp_path):
    """A PSNR series (tab:orange) lands in the PSNR panel (middle row, left), not elsewhere; without it the panel
    has no orange (negative control)."""
    def orange_pixels(data, name):
        img = cv2.imread(str(plot_report(tmp_path / name, data))).astype(np.int32)
        h, w = img.shape[:2]
        hit = (np.abs(img - np.array([14, 127, 255])).max(axis=2) <= 12)
        return int(hit[int(0.45 * h):int(0.85 * h), :w // 2].sum()), int(hit.sum())

    t = np.linspace(0.0, 2.0, 20)
    series = [PsnrSeries("first", t, 20 + np.sin(t)), PsnrSeries("second", t, 21 + np.cos(t))]
    in_panel, everywhere = orange_pixels(ReportData(psnr=series), "with.png")
    assert in_panel > 50 and in_panel == everywhere
    assert orange_pixels(ReportData(psnr=series[:1]), "without.png") == (0, 0)
