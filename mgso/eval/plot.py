"""Trajectory plot: top view of the aligned estimate over the ground truth, coloured by ATE, keyframes marked.

matplotlib (a dependency of mgso) is imported only when a plot is drawn. The figure is drawn on matplotlib's Agg
canvas directly (no pyplot, no display, no global backend switch), so it works headless and in
threads, and leaves the caller's matplotlib state alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..io.trajectory import Trajectory
from .ate import AteResult

__all__ = ["plot_trajectory", "draw_top_view", "choose_plane", "PLANES", "MatplotlibMissingError"]

PLANES: dict[str, tuple[int, int]] = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
_AXIS = "xyz"


class MatplotlibMissingError(ImportError):
    """matplotlib is needed for plots and is not installed."""


def _import_matplotlib():
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import LineCollection
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - matplotlib is a dependency of mgso
        raise MatplotlibMissingError(
            "plots need matplotlib, a dependency of mgso that is missing here: pip install matplotlib") from e
    return Figure, FigureCanvasAgg, LineCollection


def choose_plane(positions: np.ndarray) -> str:
    """The coordinate plane of the two axes with the largest extent (drops the flattest axis). For trajectories in
    the camera convention (y down, a camera moving over the ground) this is ``"xz"``."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    extent = p.max(0) - p.min(0) if len(p) else np.zeros(3)
    flat = int(np.argmin(extent))
    return {0: "yz", 1: "xz", 2: "xy"}[flat]


def plot_trajectory(path: str | Path, ate: AteResult, *, reference: Trajectory | None = None,
                    keyframe_timestamps: Sequence[float] | None = None, plane: str = "auto",
                    title: str | None = None, dpi: int = 120, size_inches: tuple[float, float] = (7.0, 6.0),
                    max_diff: float | None = None) -> Path:
    """Write a PNG top view: ground truth (grey, dashed), the aligned estimate coloured by its ATE per pose, start
    (circle) and end (square), keyframes (black dots) when ``keyframe_timestamps`` are given (matched to the aligned
    estimate within ``max_diff``, default the ATE's), and the ATE RMSE in the title.

    ``reference``: the whole ground truth to draw (default: the associated poses in ``ate``). ``plane``: ``"auto"``
    (:func:`choose_plane` on the reference), ``"xy"``, ``"xz"`` or ``"yz"``. Returns the path written.
    """
    Figure, FigureCanvasAgg, _ = _import_matplotlib()
    if plane != "auto" and plane not in PLANES:
        raise ValueError(f"plot_trajectory: plane must be 'auto' or one of {sorted(PLANES)}, got {plane!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    fig = Figure(figsize=size_inches, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    draw_top_view(ax, ate, reference=reference, keyframe_timestamps=keyframe_timestamps, plane=plane,
                  max_diff=max_diff)
    if title is None:
        what = f" ({ate.label})" if ate.label else ""
        title = f"ATE RMSE {ate.rmse:.4f} m{what}\n{ate.alignment_text}, {ate.num_pairs} poses"
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(str(path), dpi=dpi)
    return path


def draw_top_view(ax, ate: AteResult | None, *, reference: Trajectory | None = None,
                  estimate: Trajectory | None = None, keyframe_timestamps: Sequence[float] | None = None,
                  plane: str = "auto", max_diff: float | None = None, colorbar: bool = True) -> str:
    """Draw the top view of :func:`plot_trajectory` on the matplotlib axes ``ax`` (no title) and return the plane.

    With ``ate``: the ground truth (``reference``, default the associated poses) and the aligned estimate coloured
    by its per-pose ATE. Without (``ate=None``, no ground truth): ``estimate`` alone, in its own frame, with start,
    end and keyframes."""
    _, _, LineCollection = _import_matplotlib()
    if ate is None and estimate is None:
        raise ValueError("draw_top_view: give an ATE result or an estimate")
    est = ate.aligned_estimate if ate is not None else estimate
    ref = (reference if reference is not None else ate.reference) if ate is not None else None
    if plane == "auto":
        plane = choose_plane(ref.positions if ref is not None else est.positions)
    if plane not in PLANES:
        raise ValueError(f"plot_trajectory: plane must be 'auto' or one of {sorted(PLANES)}, got {plane!r}")
    a, b = PLANES[plane]
    fig = ax.figure
    ep = est.positions
    if ref is not None:
        rp = ref.positions
        ax.plot(rp[:, a], rp[:, b], "--", color="0.55", lw=1.5, label="ground truth", zorder=1)
    if ate is not None and len(ep) >= 2:
        err = ate.errors
        segs = np.stack([ep[:-1][:, [a, b]], ep[1:][:, [a, b]]], axis=1)
        lc = LineCollection(segs, cmap="viridis", linewidths=2.0, zorder=2)
        lc.set_array(0.5 * (err[:-1] + err[1:]))
        lc.set_clim(float(err.min()), float(max(err.max(), err.min() + 1e-12)))
        ax.add_collection(lc)
        if colorbar:
            cb = fig.colorbar(lc, ax=ax, fraction=0.046, pad=0.04)
            cb.set_label("ATE per pose (m)")
        ax.plot([], [], color="#21918c", lw=2, label="estimate (aligned, colour = ATE)")
    elif len(ep):
        ax.plot(ep[:, a], ep[:, b], "-", color="tab:blue", lw=1.8, label="estimate (no ground truth)", zorder=2)
    if len(ep):
        ax.plot(ep[0, a], ep[0, b], "o", color="tab:green", ms=8, mfc="none", label="start", zorder=3)
        ax.plot(ep[-1, a], ep[-1, b], "s", color="tab:red", ms=7, mfc="none", label="end", zorder=3)
    if keyframe_timestamps is not None and len(keyframe_timestamps) and len(est):
        kt = np.asarray(keyframe_timestamps, dtype=np.float64)
        tol = (ate.max_diff if ate is not None else 0.01) if max_diff is None else max_diff
        idx = np.searchsorted(est.timestamps, kt)
        idx = np.clip(idx, 0, len(est) - 1)
        left = np.clip(idx - 1, 0, len(est) - 1)
        pick = np.where(np.abs(est.timestamps[left] - kt) < np.abs(est.timestamps[idx] - kt), left, idx)
        ok = np.abs(est.timestamps[pick] - kt) <= tol
        if ok.any():
            kp = ep[pick[ok]]
            ax.plot(kp[:, a], kp[:, b], ".", color="black", ms=6, label=f"keyframes ({int(ok.sum())})", zorder=4)
    ax.set_xlabel(f"{_AXIS[a]} (m)")
    ax.set_ylabel(f"{_AXIS[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize=8)
    return plane
