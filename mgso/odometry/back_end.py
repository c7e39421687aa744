"""The window's back end as the odometry sees it: what it asks on every keyframe, in order (DSO
``FullSystemOptimize`` / ``FullSystemMarginalize``), and the one ``window.backend`` names."""

from __future__ import annotations

from typing import Any, Protocol

from ..config import Config
from ..window.depth_refine import FixedWindowBackEnd
from ..window.window import MarginalizedPoints, Window

__all__ = ["WindowBackEnd", "make_back_end"]


class WindowBackEnd(Protocol):
    """What the odometry asks of the window's back end on every keyframe (in this order)."""

    def flag_frames_for_marginalization(self, window: Window) -> list[int]:
        """Before the new keyframe is added: set ``window.flagged_`` for keyframes to remove."""

    def optimize(self, window: Window) -> Any:
        """After the new keyframe and the activation: optimise, update residual states, drop outliers."""

    def marginalize_points(self, window: Window) -> MarginalizedPoints:
        """Remove points that leave (to the point cloud or dropped)."""

    def marginalize_frames(self, window: Window) -> list[int]:
        """Remove the flagged keyframes; returns their keyframe ids."""


def make_back_end(cfg: Config, device: str = "cpu") -> WindowBackEnd:
    """The back end ``cfg.window.backend`` names: ``bundle`` (:class:`~mgso.window.backend.WindowOptimizer`) or
    ``fixed`` (:class:`~mgso.window.depth_refine.FixedWindowBackEnd`); both read ``cfg.window`` and ``cfg.tracking``
    themselves."""
    if cfg.window.backend == "fixed":
        return FixedWindowBackEnd(cfg.window, cfg.tracking)
    from ..window.backend import WindowOptimizer

    return WindowOptimizer(cfg.window, cfg.tracking, device=device)
