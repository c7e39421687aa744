"""Evaluation: trajectory accuracy (ATE / RPE, figure for figure as evo), rendering quality (PSNR / SSIM under the
MonoGS and Photo-SLAM protocols), trajectory plots, the one-page run report (``report.png``) and metric reports.

``mgso.eval.plot`` and ``mgso.eval.report_plot`` import matplotlib (a dependency of mgso) only when a figure is drawn.
"""

from .ate import (ALIGN_MODES, AteResult, ErrorStats, EvaluationError, RpeResult, associate_checked, compute_ate,
                  compute_ate_files, compute_rpe, compute_rpe_files)
from .plot import MatplotlibMissingError, choose_plane, draw_top_view, plot_trajectory
from .render_metrics import (MONOGS, PHOTO_SLAM, PROTOCOLS, SSIM_BORDERS, RenderMetrics, RenderProtocol,
                             evaluate_protocols, evaluate_renders, get_protocol, psnr, select_frames,
                             select_monogs_frames, select_photo_slam_frames, ssim, ssim_map)
from .report import format_report, metrics_report, write_metrics_json
from .report_plot import PsnrSeries, ReportData, plot_report

__all__ = [
    "ALIGN_MODES", "AteResult", "ErrorStats", "EvaluationError", "RpeResult", "associate_checked", "compute_ate",
    "compute_ate_files", "compute_rpe", "compute_rpe_files",
    "MatplotlibMissingError", "choose_plane", "draw_top_view", "plot_trajectory",
    "PsnrSeries", "ReportData", "plot_report",
    "MONOGS", "PHOTO_SLAM", "PROTOCOLS", "SSIM_BORDERS", "RenderMetrics", "RenderProtocol", "evaluate_protocols",
    "evaluate_renders", "get_protocol", "psnr", "select_frames", "select_monogs_frames", "select_photo_slam_frames",
    "ssim", "ssim_map",
    "format_report", "metrics_report", "write_metrics_json",
]
