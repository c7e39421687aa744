"""The odometry's messages to the Gaussian mapper (:mod:`mgso.messages`), made from its window (DSO's output wrapper:
one place through which every output of the odometry leaves).

Events are queued as they happen (:meth:`MapperOutbox.keyframe`, :meth:`~MapperOutbox.window`,
:meth:`~MapperOutbox.points`) and turned into messages when the frame is done (:meth:`MapperOutbox.drain`), so that
a keyframe's message carries the window's state after the whole frame (the first keyframe's points after the
window's first optimisation). Poses and points leave in the common world (:class:`~mgso.odometry.segments.Segments`).
A disabled outbox (the odometry without ``emit_messages``) queues nothing.
"""

from __future__ import annotations

import logging

import numpy as np

from ..camera import PinholeCamera
from ..geometry import se3_inverse
from ..messages import KeyframeMessage, PointsMessage, PoseUpdate
from ..window.window import MarginalizedPoints, Window
from .records import FrameRecord
from .segments import Segments

__all__ = ["MapperOutbox"]

log = logging.getLogger(__name__)


class MapperOutbox:
    """The messages of the frame being processed. ``camera``: the odometry's image geometry (the pyramid crop);
    ``mask``: the frames' valid pixels in that geometry as loss weights (``None`` when all are), set by the odometry
    when the frames' mask changes."""

    def __init__(self, window: Window, camera: PinholeCamera, segments: Segments, *, enabled: bool):
        self.window = window
        self.camera = camera
        self.segments = segments
        self.enabled = bool(enabled)
        self.mask: np.ndarray | None = None
        self._events: list = []

    def __len__(self) -> int:
        return len(self._events)

    # ------------------------------------------------------------------------------------- events
    def keyframe(self, keyframe_id: int, rec: FrameRecord, cam_to_world_world: np.ndarray) -> None:
        if self.enabled:
            self._events.append(("keyframe", (keyframe_id, rec, np.array(cam_to_world_world, np.float64))))

    def window_poses(self, keyframe_ids: list[int], cam_to_world: np.ndarray) -> None:
        if self.enabled:
            self._events.append(("window", (list(keyframe_ids), np.array(cam_to_world, np.float64))))

    def points(self, marg: MarginalizedPoints) -> None:
        if self.enabled and len(marg):
            self._events.append(("points", marg))

    # ----------------------------------------------------------------------------------- messages
    def drain(self) -> list:
        """The queued events as mapper messages, keyframes first (DSO decides a keyframe's window update and the
        points it marginalises before it announces the keyframe; the map needs the view before its poses)."""
        events, self._events = self._events, []
        kfs, rest = [], []
        for kind, ev in events:
            if kind == "keyframe":
                msg = self._keyframe_message(*ev)
                if msg is not None:
                    kfs.append(msg)
            elif kind == "window":
                rest.append(self._pose_update(*ev))
            else:
                rest += self._points_messages(ev)
        return kfs + rest

    def final(self, keyframe_ids: list[int], cam_to_world: np.ndarray, segment: int) -> list:
        """The end of the sequence: what is still queued, the final pose of every keyframe (``keyframe_ids`` with
        ``cam_to_world`` in the common world) and the points still active, in the window's newest segment (or
        ``segment`` when the window is empty)."""
        out = self.drain()
        if keyframe_ids:
            out.append(PoseUpdate({k: T for k, T in zip(keyframe_ids, cam_to_world)}))
        w = self.window
        if w.active.n:
            seg = int(w.segment_[w.order[-1]]) if w.order else segment
            pos = self.segments.points_to_world(w.points_world(), seg)
            hosts = w.keyframe_id_[w.active.host]
            for h in np.unique(hosts):
                out.append(PointsMessage(pos[hosts == h], w.active.rgb[hosts == h], host_keyframe_id=int(h)))
        return out

    def _keyframe_message(self, keyframe_id: int, rec: FrameRecord, c2w: np.ndarray) -> KeyframeMessage | None:
        """A :class:`~mgso.messages.KeyframeMessage`: the keyframe's RGB and camera in the odometry's image
        geometry (the pyramid crop), its pose in the common world, DSO's affine (a, b) and exposure time, and every
        active point of the window (depth refined by the window) projected into it (the depth map the coarse
        tracker tracks against; a new keyframe hosts no point with a depth yet); ``mask``: the frames' ``valid``
        pixels (``None`` when all are), so that the map never trains on pixels undistortion had no source for."""
        w = self.window
        try:
            slot = w.slot_of_keyframe(keyframe_id)
        except KeyError:  # marginalised within its own frame (cannot happen with DSO's rule; be safe)
            log.warning("keyframe %d left the window before it reached the map", keyframe_id)
            return None
        if w.rgb_ is None:
            raise RuntimeError("the odometry's window keeps no RGB images: the map needs them")
        pts = self.segments.points_to_world(w.points_world(), rec.segment) if w.active.n else np.zeros((0, 3))
        T = se3_inverse(c2w)
        pc = pts @ T[:3, :3].T + T[:3, 3]
        cam = self.camera
        ok = pc[:, 2] > 1e-6
        z = np.where(ok, pc[:, 2], 1.0)
        uv = np.stack([cam.fx * pc[:, 0] / z + cam.cx, cam.fy * pc[:, 1] / z + cam.cy], axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
        exposure = float(w.exposure_[slot])
        return KeyframeMessage(keyframe_id, rec.index, rec.timestamp, w.rgb_[slot], cam, c2w, uv[ok], 1.0 / z[ok],
                               affine=tuple(w.affine_[slot]), exposure_ms=exposure if exposure > 0 else None,
                               segment=rec.segment, mask=self.mask)

    def _pose_update(self, keyframe_ids: list[int], cam_to_world: np.ndarray) -> PoseUpdate:
        w = self.window
        aff = {}
        for kid in keyframe_ids:
            try:
                aff[int(kid)] = tuple(w.affine_[w.slot_of_keyframe(int(kid))])
            except KeyError:  # left the window since: its affine is the one the map has
                pass
        return PoseUpdate({int(k): T for k, T in zip(keyframe_ids, cam_to_world)}, affine=aff)

    def _points_messages(self, marg: MarginalizedPoints) -> list[PointsMessage]:
        pos = self.segments.points_to_world(marg.positions, marg.segment)
        hosts = np.asarray(marg.host_keyframe_ids)
        cols = np.asarray(marg.colors)
        return [PointsMessage(pos[hosts == h], cols[hosts == h], host_keyframe_id=int(h)) for h in np.unique(hosts)]
