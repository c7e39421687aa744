"""When a tracked frame becomes a keyframe (DSO ``FullSystem::addActiveFrame``'s "BRIGHTNESS CHECK").

A small strategy object (docs/tracking.md, "Keyframes"): thresholds from :class:`~mgso.config.TrackingConfig`,
one method that takes the tracker's result and says yes or no, with the reason as a value. DSO's rule, with ``w + h``
the image size:

``kfGlobalWeight * (maxShiftWeightT * sqrt(flow_t) + maxShiftWeightR * sqrt(flow_r) + maxShiftWeightRT *
sqrt(flow_rt)) / (w + h) + kfGlobalWeight * maxAffineWeight * |log a_rel| > 1``, or the RMSE above twice the first
RMSE against the reference, where DSO's weights are ``0.04 (640 + 480)`` etc. (so the flows count relative to the
image size) and ``a_rel`` is the brightness factor from the reference to the frame. mgso adds an optional maximum
interval in frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from ..config import TrackingConfig

__all__ = ["KeyframePolicy", "KeyframeDecision", "KeyframeReason"]

DSO_SIZE = 640 + 480  # DSO writes its shift weights as a fraction of this


class KeyframeReason(str, Enum):
    NONE = "none"
    FIRST = "first"  # the first frames of a segment (initialisation)
    FLOW = "flow"  # optical flow / brightness score above 1
    BRIGHTNESS = "brightness"  # the brightness term alone is above 1
    RMSE = "rmse"  # residual grew above kf_rmse_factor x the first RMSE
    INTERVAL = "interval"  # kf_max_interval frames since the last keyframe


@dataclass(frozen=True)
class KeyframeDecision:
    need: bool
    reason: KeyframeReason
    score: float  # DSO's weighted flow + brightness sum (a keyframe above 1)
    flow_score: float  # its flow part
    brightness_score: float  # its brightness part


@dataclass(frozen=True)
class KeyframePolicy:
    """DSO's keyframe rule; build with :meth:`from_config`."""

    width: int
    height: int
    global_weight: float = 1.0
    shift_t: float = 0.04
    shift_r: float = 0.0
    shift_rt: float = 0.02
    affine_weight: float = 2.0
    rmse_factor: float = 2.0
    max_interval: int = 0

    @classmethod
    def from_config(cls, width: int, height: int, cfg: TrackingConfig) -> "KeyframePolicy":
        return cls(width, height, cfg.kf_global_weight, cfg.kf_max_shift_t, cfg.kf_max_shift_r, cfg.kf_max_shift_rt,
                   cfg.kf_max_affine_weight, cfg.kf_rmse_factor, cfg.kf_max_interval)

    def decide(self, flow: tuple[float, float, float], a_rel: float, rmse: float, first_rmse: float,
               frames_since_keyframe: int) -> KeyframeDecision:
        """``flow``: the tracker's ``(t, r, rt)`` mean squared pixel shifts; ``a_rel``: brightness factor reference
        -> frame (``photometric.affine_from_to``); ``rmse``: the frame's level-0 RMSE; ``first_rmse``: the first
        frame's RMSE against this reference (< 0 unknown); ``frames_since_keyframe``: frames since the reference."""
        size = float(self.width + self.height)
        g = self.global_weight
        ft, fr, frt = (max(float(f), 0.0) for f in flow)
        flow_score = g * DSO_SIZE * (self.shift_t * math.sqrt(ft) + self.shift_r * math.sqrt(fr)
                                     + self.shift_rt * math.sqrt(frt)) / size
        bright = g * self.affine_weight * abs(math.log(a_rel)) if a_rel > 0 else float("inf")
        score = flow_score + bright
        if score > 1.0:
            reason = KeyframeReason.BRIGHTNESS if bright > 1.0 else KeyframeReason.FLOW
            return KeyframeDecision(True, reason, score, flow_score, bright)
        if first_rmse > 0 and self.rmse_factor * first_rmse < rmse:
            return KeyframeDecision(True, KeyframeReason.RMSE, score, flow_score, bright)
        if self.max_interval > 0 and frames_since_keyframe >= self.max_interval:
            return KeyframeDecision(True, KeyframeReason.INTERVAL, score, flow_score, bright)
        return KeyframeDecision(False, KeyframeReason.NONE, score, flow_score, bright)
