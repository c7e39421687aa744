"""``report.png``: one page that says how a full run went, drawn from values (no writer, no application wing).

Six panels on a 3 x 2 grid (:data:`REPORT_PANELS`, in reading order): the top view of the trajectory (Sim(3)-aligned
over the ground truth as in ``trajectory.png``, or the estimate alone without ground truth), the translation error
over time, the per-frame PSNR of each evaluation protocol over time, the map's Gaussians and training steps over time
(one sample per keyframe and one after the final refinement), and a text panel with the headline figures. A panel
without its data (no ground truth, no evaluation) says why instead of staying empty.

Drawn on matplotlib's Agg canvas directly, like :mod:`mgso.eval.plot` (no pyplot, no display, safe in threads).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..io.trajectory import Trajectory
from .ate import AteResult
from .plot import _import_matplotlib, draw_top_view

__all__ = ["ReportData", "PsnrSeries", "plot_report", "REPORT_PANELS", "REPORT_SIZE_INCHES", "REPORT_DPI"]

#: The panels, in reading order (row by row, two columns); the text panel spans the bottom row.
REPORT_PANELS = ("trajectory", "error", "psnr", "map", "text")
REPORT_SIZE_INCHES = (14.0, 12.5)
REPORT_DPI = 100


@dataclass(frozen=True)
class PsnrSeries:
    """Per-frame PSNR of one evaluation protocol: ``times`` (seconds from the run's first frame) and ``psnr`` (dB)."""

    label: str
    times: np.ndarray
    psnr: np.ndarray


@dataclass
class ReportData:
    """What the report draws (values only).

    ``ate``: the ATE of all frames (``None`` without ground truth); ``reference``: the whole ground truth to draw;
    ``trajectory``: the estimate (drawn alone when there is no ATE); ``keyframe_timestamps``: marked on the top view;
    ``t0``: the time origin of every time axis (seconds, the first frame's timestamp); ``psnr``: one series per
    protocol evaluated (empty: the evaluation did not run); ``map_history``: ``[K, 3]`` rows of (seconds from
    ``t0``, training steps so far, Gaussians); ``headline``: the text panel's lines; ``notes``: why a panel is empty,
    by panel name (``"psnr"``, ``"error"``)."""

    title: str = ""
    ate: AteResult | None = None
    reference: Trajectory | None = None
    trajectory: Trajectory | None = None
    keyframe_timestamps: Sequence[float] | None = None
    t0: float = 0.0
    psnr: list[PsnrSeries] = field(default_factory=list)
    map_history: np.ndarray | None = None
    headline: list[str] = field(default_factory=list)
    notes: dict[str, str] = field(default_factory=dict)


def _empty(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=11, color="0.3", wrap=True,
            transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_facecolor("0.95")


def plot_report(path: str | Path, data: ReportData, *, dpi: int = REPORT_DPI,
                size_inches: tuple[float, float] = REPORT_SIZE_INCHES) -> Path:
    """Write the one-page report of the module doc to ``path`` (PNG, ``size_inches * dpi`` pixels). Returns it."""
    Figure, FigureCanvasAgg, _ = _import_matplotlib()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=size_inches, dpi=dpi)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 2, height_ratios=(1.25, 1.0, 0.45))
    ax_traj, ax_err = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])
    ax_psnr, ax_map = fig.add_subplot(grid[1, 0]), fig.add_subplot(grid[1, 1])
    ax_text = fig.add_subplot(grid[2, :])

    # trajectory
    if data.ate is not None or (data.trajectory is not None and len(data.trajectory)):
        draw_top_view(ax_traj, data.ate, reference=data.reference, estimate=data.trajectory,
                      keyframe_timestamps=data.keyframe_timestamps)
        ax_traj.set_title("top view, Sim(3)-aligned to the ground truth" if data.ate is not None
                          else "top view (no ground truth: the estimate in its own frame)", fontsize=10)
    else:
        _empty(ax_traj, "no pose estimated")

    # translation error over time
    if data.ate is not None:
        t = data.ate.aligned_estimate.timestamps - data.t0
        ax_err.plot(t, data.ate.errors, "-", color="tab:purple", lw=1.4)
        ax_err.axhline(data.ate.rmse, color="0.4", ls="--", lw=1,
                       label=f"RMSE {data.ate.rmse:.4f} m ({data.ate.num_pairs} poses)")
        ax_err.set_xlabel("time (s)")
        ax_err.set_ylabel("translation error (m)")
        ax_err.set_ylim(bottom=0)
        ax_err.grid(True, lw=0.4, alpha=0.5)
        ax_err.legend(loc="best", fontsize=8)
        ax_err.set_title("ATE per pose over time (all frames)", fontsize=10)
    else:
        _empty(ax_err, data.notes.get("error", "no ground truth: no trajectory error"))

    # PSNR over time
    if data.psnr:
        for s, colour in zip(data.psnr, ("tab:blue", "tab:orange", "tab:green", "tab:red")):
            ax_psnr.plot(s.times, s.psnr, ".-", color=colour, lw=1, ms=5,
                         label=f"{s.label}: mean {float(np.mean(s.psnr)):.2f} dB ({len(s.psnr)} frames)")
        ax_psnr.set_xlabel("time (s)")
        ax_psnr.set_ylabel("PSNR (dB)")
        ax_psnr.grid(True, lw=0.4, alpha=0.5)
        ax_psnr.legend(loc="best", fontsize=8)
        ax_psnr.set_title("rendering quality per evaluated frame", fontsize=10)
    else:
        _empty(ax_psnr, data.notes.get("psnr", "no rendering evaluation"))

    # the map over time
    h = None if data.map_history is None else np.asarray(data.map_history, np.float64).reshape(-1, 3)
    if h is not None and len(h):
        ax_map.step(h[:, 0], h[:, 2], where="post", color="tab:green", lw=1.6, marker=".", label="Gaussians")
        ax_map.set_xlabel("time (s)")
        ax_map.set_ylabel("Gaussians", color="tab:green")
        ax_map.grid(True, lw=0.4, alpha=0.5)
        ax2 = ax_map.twinx()
        ax2.plot(h[:, 0], h[:, 1], "-", color="tab:brown", lw=1.4, marker="x", ms=4, label="training steps")
        ax2.set_ylabel("training steps so far", color="tab:brown")
        lines = ax_map.get_lines() + ax2.get_lines()
        ax_map.legend(lines, [ln.get_label() for ln in lines], loc="upper left", fontsize=8)
        ax_map.set_title("the map per keyframe (last point: after the final refinement)", fontsize=10)
    else:
        _empty(ax_map, data.notes.get("map", "no keyframe reached the map"))

    # headline figures
    ax_text.axis("off")
    ax_text.set_facecolor("white")
    ax_text.text(0.01, 0.97, "\n".join(data.headline) if data.headline else "(no figures)", ha="left", va="top",
                 family="monospace", fontsize=10.5, transform=ax_text.transAxes)
    if data.title:
        fig.suptitle(data.title, fontsize=13)
    fig.tight_layout()
    fig.savefig(str(path), dpi=dpi)
    return path
