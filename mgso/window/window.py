"""The sliding window: the one owner of the keyframes in it, their immature and active points, and the
marginalised point cloud (DSO's ``FullSystem::frameHessians`` with each frame's ``immaturePoints`` /
``pointHessians``, and ``EnergyFunctional``'s point storage).

Layout (docs/window.md: one owner, capacity-bounded struct-of-arrays, views of the live part):

- **Keyframes** live in ``capacity`` slots (``window.max_frames + 1``: DSO adds the new keyframe before it drops the
  ones flagged for marginalisation, so the window briefly holds one more). A slot is an index into every per-keyframe
  array (``world_to_cam_[slot]``, ``pyramids[slot]``, ...). :attr:`Window.order` lists the live slots oldest first
  (DSO's ``frameHessians`` order); ``order[-1]`` is the newest keyframe. Slots are reused after a keyframe leaves.
- **Immature points** (:class:`ImmaturePoints`) and **active points** (:class:`ActivePoints`) are struct-of-arrays:
  one NumPy array per field of full capacity (trailing underscore, ``host_``) and a property of the same name without
  the underscore for the live part (``host`` = ``host_[:n]``). Points are kept packed (``0..n-1``); removing points
  compacts them in order (:meth:`PointBuffer.keep`). A point refers to its host keyframe by **slot**.
- Per point and target keyframe, active points keep the residual bookkeeping (``res_state [n, capacity]``, one
  column per slot, :class:`ResidualState`; ``NONE`` where no residual exists, e.g. the host's own column).
- The **marginalised point cloud** (:class:`PointCloud`) grows for the whole run (world positions and colours): MGSO
  seeds Gaussians from it.

Kernels read the buffers directly: :meth:`PointBuffer.warp` gives a ``wp.array`` of a field's live part. On the CPU it
is a zero-copy view of the NumPy storage (``wp.array(..., copy=False)``), so a kernel writes straight into the
window; on a CUDA device it is a device mirror, filled by :meth:`PointBuffer.to_device` and read back by
:meth:`PointBuffer.from_device` (both no-ops on the CPU).

Who may change what (DSO's ``FullSystem.h`` habit; the same text is next to each field):

==============================  ===========================================================================
field                           changed only by
==============================  ===========================================================================
slots, ``order``, frame ids,    :meth:`Window.add_keyframe` and :meth:`Window.remove_keyframe` (the odometry's
pyramids, ``dI0_``, ``rgb_``,   keyframe step; the back end's frame marginalisation)
exposure
``world_to_cam_``, ``affine_``  the back end's optimisation (``set_keyframe_state``); :meth:`add_keyframe` sets the
                                initial value from the tracker
``world_to_cam_zero_``,         the back end when it fixes a linearisation point (``set_linearization_point``);
``affine_zero_``                :meth:`add_keyframe` sets them to the initial value
``flagged_``                    the back end's ``flag_frames_for_marginalization``
``points_left_``                :meth:`Window.marginalize_points`, :meth:`Window.drop_points` (counters)
``energy_th_``                  the back end (DSO ``setNewFrameEnergyTH``)
immature points                 :meth:`ImmaturePoints.append` (new keyframe, pixel selector), the trace step
                                (``idepth_min/max``, ``quality``, ``status``, ``pixel_interval``, ``trace_uv``,
                                ``energy``), activation and :meth:`Window.remove_keyframe` (removal)
active points: ``idepth``,      the back end's optimisation (and the initialiser / activation that create them)
``idepth_hessian``
``idepth_zero``                 activation/initialisation; the back end when it fixes the linearisation point
``res_state``, ``res_energy``   :meth:`Window.add_keyframe` (new column ``IN``), the back end (linearisation,
                                outliers), :meth:`Window.remove_keyframe` (column cleared)
``flag``                        the back end (``MARGINALIZE`` / ``DROP`` before :meth:`Window.remove_flagged_points`)
everything else of a point      set once when it is created
point cloud                     :meth:`Window.marginalize_points` (append only)
==============================  ===========================================================================
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import warp as wp

from mgso_kernels.image import ImagePyramid, Pinhole, PyramidGeometry
from mgso_kernels import runtime
from mgso_kernels.photometric import PATTERN_NP, affine_from_to
from ..geometry import se3_renormalize

__all__ = [
    "Window", "WindowFullError", "PointBuffer", "Field", "ImmaturePoints", "ActivePoints", "PointCloud",
    "ResidualState", "PointFlag", "MarginalizedPoints",
]

log = logging.getLogger(__name__)


class WindowFullError(RuntimeError):
    """A capacity-bounded buffer of the window is full (raise the capacity in the config)."""


class ResidualState(IntEnum):
    """State of a point's residual in one target keyframe (``ActivePoints.res_state``)."""

    NONE = 0  # no residual (the host's own column, a free slot, or a keyframe added after the point was dropped)
    IN = 1  # active residual (DSO ResState::IN)
    OOB = 2  # projects out of the target image (DSO ResState::OOB)
    OUTLIER = 3  # energy above the threshold (DSO ResState::OUTLIER)


class PointFlag(IntEnum):
    """What the back end decided for an active point (DSO ``EFPointStatus``)."""

    KEEP = 0  # stays active (PS_GOOD)
    MARGINALIZE = 1  # leaves the window into the point cloud (PS_MARGINALIZE)
    DROP = 2  # leaves the window and is forgotten (PS_DROP)


# ----------------------------------------------------------------------------------------------- SoA buffers
class Field:
    """A per-point field of a :class:`PointBuffer`: full-capacity storage ``<name>_`` and a live view ``<name>``.

    ``dtype`` is the NumPy dtype, ``tail`` the per-point shape, ``wp_dtype`` the Warp dtype of :meth:`PointBuffer.warp`
    (``wp.vec2`` for ``tail=(2,)``, ...), ``fill`` the value of unused entries.
    """

    def __init__(self, dtype, tail: tuple = (), fill=0, wp_dtype=None, doc: str = ""):
        self.dtype = np.dtype(dtype)
        self.tail = tuple(tail)
        self.fill = fill
        self.wp_dtype = wp_dtype
        self.__doc__ = doc
        self.name = ""

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        return getattr(obj, self.name + "_")[: obj.n]


class PointBuffer:
    """Capacity-bounded struct of arrays (DPVO ``patchgraph`` style). Subclasses declare :class:`Field` attributes.

    ``n`` points are live, packed at ``0..n-1``. Nothing reallocates: :meth:`append` past ``capacity`` raises
    :class:`WindowFullError`.
    """

    kind = "points"

    def __init__(self, capacity: int, *, columns: int = 0, device: str | None = None):
        if capacity < 1:
            raise ValueError(f"{type(self).__name__}: capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.columns = int(columns)
        self.device = runtime.device_or_cpu(device)
        self.n = 0
        self._wp_full: dict[str, wp.array] = {}
        for f in self.fields():
            tail = tuple(self.columns if t == "K" else t for t in f.tail)
            setattr(self, f.name + "_", np.full((self.capacity,) + tail, f.fill, dtype=f.dtype))

    @classmethod
    def fields(cls) -> list[Field]:
        out = []
        for klass in reversed(cls.__mro__):
            out += [v for v in vars(klass).values() if isinstance(v, Field)]
        return out

    def __len__(self) -> int:
        return self.n

    @property
    def free(self) -> int:
        return self.capacity - self.n

    def append(self, count: int, **values) -> slice:
        """Add ``count`` points; ``values`` give some fields (arrays of length ``count`` or scalars), the others get
        their fill value. Returns the slice of the new points."""
        count = int(count)
        if count < 0:
            raise ValueError("count must be >= 0")
        if self.n + count > self.capacity:
            raise WindowFullError(f"{self.kind}: {self.n} + {count} points exceed the capacity {self.capacity}")
        names = {f.name for f in self.fields()}
        unknown = set(values) - names
        if unknown:
            raise TypeError(f"{type(self).__name__}.append: unknown field(s) {sorted(unknown)}")
        sl = slice(self.n, self.n + count)
        for f in self.fields():
            arr = getattr(self, f.name + "_")
            arr[sl] = values[f.name] if f.name in values else f.fill
        self.n += count
        return sl

    def keep(self, mask: np.ndarray) -> np.ndarray:
        """Keep the live points where ``mask`` is true, packed in their order; the freed tail gets fill values.
        Returns the old index of each kept point."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self.n,):
            raise ValueError(f"keep: mask must have shape ({self.n},), got {mask.shape}")
        idx = np.flatnonzero(mask)
        m = len(idx)
        if m == self.n:
            return idx
        for f in self.fields():
            arr = getattr(self, f.name + "_")
            arr[:m] = arr[idx]
            arr[m:self.n] = f.fill
        self.n = m
        return idx

    def clear(self) -> None:
        self.keep(np.zeros(self.n, dtype=bool))

    # ------------------------------------------------------------------------------------- Warp views
    def _full(self, name: str) -> wp.array:
        w = self._wp_full.get(name)
        if w is None:
            f = type(self).__dict__.get(name) or next(x for x in self.fields() if x.name == name)
            arr = getattr(self, name + "_")
            wdt = f.wp_dtype or wp.dtype_from_numpy(arr.dtype)
            if wp.get_device(self.device).is_cpu:
                w = wp.array(arr, dtype=wdt, device="cpu", copy=False)
            else:  # a vector dtype (vec2, vec3) takes the last axis
                shape = arr.shape[:-1] if f.wp_dtype is not None and f.tail else arr.shape
                w = wp.zeros(shape, dtype=wdt, device=self.device)
            self._wp_full[name] = w
        return w

    def warp(self, name: str) -> wp.array:
        """``wp.array`` of the live part of field ``name`` (zero-copy on the CPU; the device mirror on CUDA)."""
        return self._full(name)[: self.n]

    def to_device(self, *names: str) -> None:
        """Copy the live part of fields to the device mirror (no-op on the CPU)."""
        if wp.get_device(self.device).is_cpu or self.n == 0:
            return
        for name in names:
            arr = getattr(self, name + "_")[: self.n]
            self._full(name)[: self.n].assign(np.ascontiguousarray(arr))

    def from_device(self, *names: str) -> None:
        """Copy the device mirror's live part of fields back to the NumPy storage (no-op on the CPU)."""
        if wp.get_device(self.device).is_cpu or self.n == 0:
            return
        for name in names:
            getattr(self, name + "_")[: self.n] = self._full(name)[: self.n].numpy().reshape(
                getattr(self, name + "_")[: self.n].shape)


class ImmaturePoints(PointBuffer):
    """Candidate points whose inverse depth is an interval refined by the epipolar trace (DSO ``ImmaturePoint``).

    Created by :meth:`append` when a keyframe is made (pixel selector + host pattern); the trace step updates the
    interval fields on every new frame; activation turns good ones into :class:`ActivePoints` and removes them.
    """

    kind = "immature points"
    host = Field(np.int32, (), -1, doc="host keyframe slot. Set at creation.")
    uv = Field(np.float32, (2,), 0.0, wp.vec2, doc="host pixel (level 0). Set at creation.")
    type = Field(np.int32, (), 1, doc="selection level as DSO's my_type: 1, 2, 4 (level 0, 1, 2). Set at creation.")
    color = Field(np.float32, (8,), 0.0, doc="host intensity at the 8 pattern pixels. Set at creation.")
    weight = Field(np.float32, (8,), 0.0, doc="host gradient weight sqrt(c2/(c2+|grad|^2)) per pattern pixel. "
                                              "Set at creation.")
    grad_h = Field(np.float32, (3,), 0.0, wp.vec3, doc="sum over the pattern of (gx^2, gx gy, gy^2) (DSO gradH). "
                                                      "Set at creation.")
    idepth_min = Field(np.float32, (), 0.0, doc="inverse-depth interval low end. Trace step.")
    idepth_max = Field(np.float32, (), np.nan, doc="inverse-depth interval high end, NaN = unknown. Trace step.")
    quality = Field(np.float32, (), 10000.0, doc="second-best / best energy of the search (DSO quality). Trace.")
    status = Field(np.int32, (), 5, doc="last trace status (mgso_kernels.trace.TraceStatus). Trace step.")
    pixel_interval = Field(np.float32, (), 0.0, doc="length of the interval in the last traced frame, pixels (DSO "
                                                    "lastTracePixelInterval). Trace step.")
    trace_uv = Field(np.float32, (2,), -1.0, wp.vec2, doc="best match in the last traced frame. Trace step.")
    energy = Field(np.float32, (), np.nan, doc="energy of the last trace. Trace step.")

    @property
    def idepth_mid(self) -> np.ndarray:
        """``0.5 (idepth_min + idepth_max)``, DSO's starting inverse depth at activation."""
        return 0.5 * (self.idepth_min + self.idepth_max)


class ActivePoints(PointBuffer):
    """Points with one inverse depth, optimised in the window (DSO ``PointHessian``). ``res_state``/``res_energy``
    have one column per keyframe slot (the point's residual in that target)."""

    kind = "active points"
    point_id = Field(np.int64, (), -1, doc="unique id over the run. Set at creation.")
    host = Field(np.int32, (), -1, doc="host keyframe slot. Set at creation.")
    uv = Field(np.float32, (2,), 0.0, wp.vec2, doc="host pixel (level 0). Set at creation.")
    type = Field(np.int32, (), 1, doc="selection level as DSO's my_type (1, 2, 4). Set at creation.")
    color = Field(np.float32, (8,), 0.0, doc="host intensity at the pattern pixels. Set at creation.")
    weight = Field(np.float32, (8,), 0.0, doc="host gradient weight per pattern pixel. Set at creation.")
    rgb = Field(np.float32, (3,), 0.0, wp.vec3, doc="colour in [0, 1]: mean over the pattern of the host RGB image. "
                                                   "Set at creation.")
    idepth = Field(np.float32, (), 0.0, doc="inverse depth in the host (current estimate). Back end.")
    idepth_zero = Field(np.float32, (), 0.0, doc="first-estimate linearisation point (DSO idepth_zero). Set at "
                                                 "creation; the back end when it fixes linearisation.")
    idepth_hessian = Field(np.float32, (), 0.0, doc="Hessian of the point's energy in its inverse depth (sum of "
                                                    "w J_d^2 over its IN residuals). Back end.")
    has_depth_prior = Field(np.bool_, (), False, doc="from the initialiser: the window adds DSO's idepth prior. "
                                                     "Set at creation.")
    num_good_residuals = Field(np.int32, (), 0, doc="residuals that were ever IN (DSO numGoodResiduals). Back end.")
    flag = Field(np.int8, (), 0, doc="PointFlag: KEEP, or what to do at the next removal. Back end.")
    res_state = Field(np.uint8, ("K",), 0, doc="[n, slots] ResidualState per target keyframe slot. add_keyframe "
                                               "(IN), back end, remove_keyframe (NONE).")
    res_energy = Field(np.float32, ("K",), 0.0, doc="[n, slots] last energy of that residual. Back end.")

    def num_residuals(self, state: ResidualState = ResidualState.IN) -> np.ndarray:
        """``[n]`` residuals of each point in ``state``."""
        return np.count_nonzero(self.res_state == int(state), axis=1)


@dataclass(frozen=True)
class MarginalizedPoints:
    """Points that left the window in one step (what ``on_points_marginalized`` carries)."""

    positions: np.ndarray  # [M, 3] float32 world
    colors: np.ndarray  # [M, 3] float32 in [0, 1]
    point_ids: np.ndarray  # [M] int64
    host_keyframe_ids: np.ndarray  # [M] int64 keyframe id of the host
    segment: int  # tracking segment the points belong to

    def __len__(self) -> int:
        return int(self.positions.shape[0])


class PointCloud:
    """The marginalised points of the whole run (append only; grows in chunks, folded into one set of arrays when
    read, so that the points are held once: profiles/memory.py measured a second copy when the chunks were kept
    beside their concatenation)."""

    def __init__(self):
        self._chunks: list[MarginalizedPoints] = []
        self._base: tuple = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                             np.zeros(0, np.int64), np.zeros(0, np.int64))

    def append(self, pts: MarginalizedPoints) -> None:
        if len(pts):
            self._chunks.append(pts)

    def __len__(self) -> int:
        return int(self._base[0].shape[0]) + sum(len(c) for c in self._chunks)

    def _cat(self):
        if self._chunks:
            ch, self._chunks = self._chunks, []
            b = self._base
            self._base = (np.concatenate([b[0]] + [c.positions for c in ch]),
                          np.concatenate([b[1]] + [c.colors for c in ch]),
                          np.concatenate([b[2]] + [c.point_ids for c in ch]),
                          np.concatenate([b[3]] + [np.full(len(c), c.segment, np.int64) for c in ch]),
                          np.concatenate([b[4]] + [np.asarray(c.host_keyframe_ids, np.int64) for c in ch]))
        return self._base

    @property
    def positions(self) -> np.ndarray:
        return self._cat()[0]

    @property
    def colors(self) -> np.ndarray:
        return self._cat()[1]

    @property
    def point_ids(self) -> np.ndarray:
        return self._cat()[2]

    @property
    def segments(self) -> np.ndarray:
        return self._cat()[3]

    @property
    def host_keyframe_ids(self) -> np.ndarray:
        return self._cat()[4]


# ---------------------------------------------------------------------------------------------------- window
class Window:
    """Keyframes of the sliding window and their points (see the module text for who changes what).

    ``geometry``: the level-0 pyramid geometry shared by all frames (size, levels, intrinsics after the crop).
    ``max_frames``: keyframes kept after marginalisation (DSO ``setting_maxFrames`` = 7); the window has
    ``max_frames + 1`` slots. ``point_capacity`` / ``immature_capacity``: sizes of the point buffers.
    """

    def __init__(self, geometry: PyramidGeometry, *, max_frames: int = 7, point_capacity: int = 8000,
                 immature_capacity: int = 16000, device: str | None = None, keep_rgb: bool = True):
        if geometry.camera is None:
            raise ValueError("Window needs a PyramidGeometry with intrinsics (plan_pyramid(..., camera=...))")
        if not 2 <= max_frames <= 16:
            raise ValueError(f"max_frames must be in [2, 16], got {max_frames}")
        self.geometry = geometry
        self.device = runtime.device_or_cpu(device)
        self.max_frames = int(max_frames)
        self.capacity = self.max_frames + 1
        K = self.capacity
        w, h = geometry.width, geometry.height
        # -- per keyframe slot. ONLY changed by add_keyframe / remove_keyframe unless said otherwise.
        self.used_ = np.zeros(K, dtype=bool)  # slot holds a keyframe
        self.frame_index_ = np.full(K, -1, dtype=np.int64)  # index of the frame in the input sequence (DSO shell id)
        self.keyframe_id_ = np.full(K, -1, dtype=np.int64)  # running keyframe number of the run (DSO frameID)
        self.timestamp_ = np.zeros(K, dtype=np.float64)  # seconds
        self.exposure_ = np.zeros(K, dtype=np.float64)  # exposure time (ms); 0 = unknown
        self.segment_ = np.zeros(K, dtype=np.int64)  # tracking segment (a new one after each tracking loss)
        # current estimate: set by add_keyframe, then ONLY changed by the back end (set_keyframe_state)
        self.world_to_cam_ = np.tile(np.eye(4), (K, 1, 1))  # [K, 4, 4] float64
        self.affine_ = np.zeros((K, 2), dtype=np.float64)  # (a, b): I_frame = exp(a) I_global + b
        # first-estimate linearisation point: set by add_keyframe, then ONLY by the back end (set_linearization_point)
        self.world_to_cam_zero_ = np.tile(np.eye(4), (K, 1, 1))
        self.affine_zero_ = np.zeros((K, 2), dtype=np.float64)
        # ONLY changed by the back end
        self.flagged_ = np.zeros(K, dtype=bool)  # flagged for marginalisation (DSO flaggedForMarginalization)
        self.energy_th_ = np.full(K, 8 * 144.0)  # DSO frameEnergyTH (per point-frame residual, 8 pixels)
        # ONLY changed by marginalize_points / remove_flagged_points: active points of the slot that left the window
        # (DSO pointHessiansMarginalized.size() + pointHessiansOut.size(); the 5 % rule of marginalisation)
        self.points_left_ = np.zeros(K, dtype=np.int64)
        # images: pyramids copied in by add_keyframe; RGB (level 0 size) for point colours
        self.pyramids = [ImagePyramid(geometry, device=device) for _ in range(K)]
        # the level-0 (I, dx, dy) of every slot in one [K, h, w] array (each pyramid's dI[0] is a view of its row):
        # the bundle adjustment's kernel reads all targets in one launch
        l0w, l0h = geometry.level_size(0)
        self.dI0_ = wp.zeros((K, l0h, l0w), dtype=wp.vec3, device=device)
        for s, pyr in enumerate(self.pyramids):
            pyr.dI[0] = self.dI0_[s]
        self.rgb_ = np.zeros((K, h, w, 3), dtype=np.float32) if keep_rgb else None
        self.order: list[int] = []  # live slots, oldest first (DSO frameHessians order)
        self._next_keyframe_id = 0
        self._next_point_id = 0
        # points
        self.immature = ImmaturePoints(immature_capacity, device=device)
        self.active = ActivePoints(point_capacity, columns=K, device=device)
        self.cloud = PointCloud()

    # ------------------------------------------------------------------------------------------- queries
    @property
    def num_keyframes(self) -> int:
        return len(self.order)

    @property
    def newest_slot(self) -> int:
        if not self.order:
            raise IndexError("the window has no keyframes")
        return self.order[-1]

    @property
    def camera(self) -> Pinhole:
        """Level-0 intrinsics (after the pyramid crop)."""
        return self.geometry.camera

    @property
    def width(self) -> int:
        return self.geometry.width

    @property
    def height(self) -> int:
        return self.geometry.height

    def K(self, level: int = 0) -> np.ndarray:
        return self.geometry.level_camera(level).matrix()

    def cam_to_world(self, slot: int) -> np.ndarray:
        return _inverse(self.world_to_cam_[slot])

    def target_from_host(self, host: int, target: int, zero: bool = False) -> np.ndarray:
        """``world_to_cam[target] @ cam_to_world[host]`` (DSO ``hostToTarget``); ``zero``: at the linearisation
        points."""
        T = self.world_to_cam_zero_ if zero else self.world_to_cam_
        return T[target] @ _inverse(T[host])

    def affine_rel(self, host: int, target: int) -> tuple[float, float]:
        """``(a_rel, b_rel)`` with ``I_target ~ a_rel I_host + b_rel`` (DSO ``fromToVecExposure``)."""
        a_h, b_h = self.affine_[host]
        a_t, b_t = self.affine_[target]
        return affine_from_to(a_h, b_h, a_t, b_t, self.exposure_[host], self.exposure_[target])

    def slot_of_keyframe(self, keyframe_id: int) -> int:
        hit = np.flatnonzero(self.used_ & (self.keyframe_id_ == keyframe_id))
        if not len(hit):
            raise KeyError(f"keyframe {keyframe_id} is not in the window")
        return int(hit[0])

    def position(self, slot: int) -> int:
        """Index of ``slot`` in :attr:`order` (0 = oldest)."""
        return self.order.index(slot)

    # ---------------------------------------------------------------------------------------- keyframes
    def add_keyframe(self, *, frame_index: int, timestamp: float, world_to_cam: np.ndarray,
                     affine=(0.0, 0.0), exposure: float = 0.0, pyramid: ImagePyramid,
                     rgb: np.ndarray | None = None, segment: int = 0) -> int:
        """Put a new keyframe in a free slot (newest in :attr:`order`); returns the slot.

        Copies ``pyramid`` (same geometry) into the slot's pyramid and ``rgb [H, W, 3]`` (level-0 size, already
        cropped) into ``rgb_``. Every active point hosted elsewhere gets an ``IN`` residual in the new keyframe (DSO
        ``makeKeyFrame``: "add new residuals for old points"). Raises :class:`WindowFullError` when all slots are used.
        """
        free = np.flatnonzero(~self.used_)
        if not len(free):
            raise WindowFullError(f"the window already holds {self.capacity} keyframes (max_frames "
                                  f"{self.max_frames} + 1): marginalise before adding")
        if pyramid.geometry != self.geometry:
            raise ValueError("add_keyframe: the pyramid's geometry differs from the window's")
        T = np.asarray(world_to_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("add_keyframe: world_to_cam must be a finite 4x4 matrix")
        s = int(free[0])
        self.used_[s] = True
        self.frame_index_[s] = int(frame_index)
        self.keyframe_id_[s] = self._next_keyframe_id
        self._next_keyframe_id += 1
        self.timestamp_[s] = float(timestamp)
        self.exposure_[s] = float(exposure or 0.0)
        self.segment_[s] = int(segment)
        T = se3_renormalize(T)
        self.world_to_cam_[s] = T
        self.world_to_cam_zero_[s] = T
        self.affine_[s] = affine
        self.affine_zero_[s] = affine
        self.flagged_[s] = False
        self.energy_th_[s] = 8 * 144.0
        self.points_left_[s] = 0
        dst = self.pyramids[s]
        for lvl in range(self.geometry.levels):
            wp.copy(dst.intensity[lvl], pyramid.intensity[lvl])
            wp.copy(dst.dI[lvl], pyramid.dI[lvl])
            wp.copy(dst.grad_sq[lvl], pyramid.grad_sq[lvl])
        if self.rgb_ is not None:
            if rgb is None:
                self.rgb_[s] = 0.0
            else:
                rgb = np.asarray(rgb, dtype=np.float32)
                if rgb.shape != self.rgb_.shape[1:]:
                    raise ValueError(f"add_keyframe: rgb must be {self.rgb_.shape[1:]}, got {rgb.shape}")
                self.rgb_[s] = rgb
        self.order.append(s)
        a = self.active
        a.res_state_[: a.n, s] = ResidualState.IN
        a.res_state_[: a.n, s][a.host == s] = ResidualState.NONE  # (no point is hosted in a fresh slot)
        a.res_energy_[: a.n, s] = 0.0
        return s

    def remove_keyframe(self, slot: int) -> None:
        """Take a keyframe out of the window: its immature points are dropped, every residual that targets it is
        cleared. Its active points must have been removed first (:meth:`marginalize_points` /
        :meth:`remove_flagged_points`): a hosted active point left is an error (it would lose its host)."""
        if not (0 <= slot < self.capacity) or not self.used_[slot]:
            raise KeyError(f"slot {slot} holds no keyframe")
        a = self.active
        if np.any(a.host == slot):
            raise RuntimeError(f"remove_keyframe: slot {slot} still hosts {int(np.sum(a.host == slot))} active points; "
                               "marginalise or drop them first")
        self.immature.keep(self.immature.host != slot)
        a.res_state_[: a.n, slot] = ResidualState.NONE
        a.res_energy_[: a.n, slot] = 0.0
        self.used_[slot] = False
        self.flagged_[slot] = False
        self.frame_index_[slot] = -1
        self.keyframe_id_[slot] = -1
        self.order.remove(slot)

    def clear(self) -> None:
        """Remove every keyframe and point (a new tracking segment starts). The point cloud is kept."""
        self.active.clear()
        self.immature.clear()
        for s in list(self.order):
            self.remove_keyframe(s)

    def set_keyframe_state(self, slot: int, world_to_cam: np.ndarray | None = None, affine=None) -> None:
        """The back end's way to move a keyframe's current estimate."""
        if world_to_cam is not None:
            T = np.asarray(world_to_cam, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError("set_keyframe_state: world_to_cam must be a finite 4x4 matrix")
            self.world_to_cam_[slot] = se3_renormalize(T)
        if affine is not None:
            self.affine_[slot] = affine

    def set_keyframe_states(self, slots: np.ndarray, world_to_cam: np.ndarray, affine: np.ndarray) -> None:
        """:meth:`set_keyframe_state` for several slots at once (``world_to_cam [k, 4, 4]``, ``affine [k, 2]``): the
        same result, one batched renormalisation instead of one a slot."""
        slots = np.asarray(slots, dtype=np.int64)
        T = np.asarray(world_to_cam, dtype=np.float64)
        if T.shape != (len(slots), 4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("set_keyframe_states: world_to_cam must be finite 4x4 matrices, one a slot")
        self.world_to_cam_[slots] = se3_renormalize(T)
        self.affine_[slots] = affine

    def set_linearization_point(self, slot: int) -> None:
        """Fix a keyframe's first-estimate linearisation point at its current estimate."""
        self.world_to_cam_zero_[slot] = self.world_to_cam_[slot]
        self.affine_zero_[slot] = self.affine_[slot]

    # ------------------------------------------------------------------------------------------- points
    def new_point_ids(self, count: int) -> np.ndarray:
        ids = np.arange(self._next_point_id, self._next_point_id + count, dtype=np.int64)
        self._next_point_id += count
        return ids

    def add_active_points(self, *, host: np.ndarray, uv: np.ndarray, idepth: np.ndarray, color: np.ndarray,
                          weight: np.ndarray, type: np.ndarray | int = 1, res_state: np.ndarray | None = None,
                          has_depth_prior: bool = False, idepth_hessian: np.ndarray | float = 0.0) -> slice:
        """Create active points (initialiser, activation). ``res_state [m, slots]`` defaults to ``IN`` in every
        live keyframe but the host. The colour is the mean of the host RGB image over the pattern."""
        host = np.asarray(host, dtype=np.int32).reshape(-1)
        m = len(host)
        if m == 0:
            return slice(self.active.n, self.active.n)
        if not np.all(self.used_[host]):
            raise ValueError("add_active_points: a host slot holds no keyframe")
        uv = np.asarray(uv, dtype=np.float32).reshape(m, 2)
        if res_state is None:
            res_state = np.zeros((m, self.capacity), dtype=np.uint8)
            res_state[:, self.order] = ResidualState.IN
            res_state[np.arange(m), host] = ResidualState.NONE
        idepth = np.asarray(idepth, dtype=np.float32).reshape(m)
        return self.active.append(
            m, point_id=self.new_point_ids(m), host=host, uv=uv, type=type, color=color, weight=weight,
            rgb=self.pattern_rgb(host, uv), idepth=idepth, idepth_zero=idepth, idepth_hessian=idepth_hessian,
            has_depth_prior=has_depth_prior, res_state=res_state)

    def pattern_rgb(self, host: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``[m, 3]`` mean of the host RGB image over the 8 pattern pixels (nearest pixel), 0.5 gray without RGB."""
        m = len(host)
        if self.rgb_ is None or m == 0:
            return np.full((m, 3), 0.5, np.float32)
        x = np.clip(np.rint(uv[:, None, 0] + PATTERN_NP[None, :, 0]).astype(np.int64), 0, self.width - 1)
        y = np.clip(np.rint(uv[:, None, 1] + PATTERN_NP[None, :, 1]).astype(np.int64), 0, self.height - 1)
        return self.rgb_[np.asarray(host)[:, None], y, x].mean(axis=1).astype(np.float32)

    def points_world(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """``[m, 3]`` world positions of active points (all live ones by default), float64."""
        a = self.active
        idx = np.arange(a.n) if index is None else np.arange(a.n)[index]
        out = np.zeros((len(idx), 3))
        host = a.host[idx]
        cam = self.camera
        for s in np.unique(host):
            sel = host == s
            uv = a.uv[idx[sel]].astype(np.float64)
            d = 1.0 / a.idepth[idx[sel]].astype(np.float64)
            pc = np.stack([(uv[:, 0] - cam.cx) / cam.fx * d, (uv[:, 1] - cam.cy) / cam.fy * d, d], axis=1)
            c2w = self.cam_to_world(int(s))
            out[sel] = pc @ c2w[:3, :3].T + c2w[:3, 3]
        return out

    def marginalize_points(self, mask: np.ndarray) -> MarginalizedPoints:
        """Move the active points where ``mask`` is true (and whose inverse depth is positive) into the point cloud
        and remove them from the window. Returns what was added."""
        a = self.active
        mask = np.asarray(mask, dtype=bool) & (a.idepth > 0) & np.isfinite(a.idepth)
        idx = np.flatnonzero(mask)
        seg = int(self.segment_[self.order[-1]]) if self.order else 0
        out = MarginalizedPoints(self.points_world(idx).astype(np.float32), a.rgb[idx].copy(),
                                 a.point_id[idx].copy(), self.keyframe_id_[a.host[idx]].copy(), seg)
        self.cloud.append(out)
        self._count_left(mask)
        a.keep(~mask)
        return out

    def drop_points(self, mask: np.ndarray) -> int:
        """Forget the active points where ``mask`` is true (outliers); returns how many."""
        mask = np.asarray(mask, dtype=bool)
        self._count_left(mask)
        self.active.keep(~mask)
        return int(mask.sum())

    def _count_left(self, mask: np.ndarray) -> None:
        if mask.any():
            self.points_left_ += np.bincount(self.active.host[mask], minlength=self.capacity)[: self.capacity]

    def points_in(self, slot: int) -> int:
        """Active + immature points hosted in ``slot`` (DSO's ``in`` of the 5 % rule)."""
        return int(np.sum(self.active.host == slot) + np.sum(self.immature.host == slot))

    def remove_flagged_points(self) -> MarginalizedPoints:
        """Apply the back end's ``flag``: ``MARGINALIZE`` -> point cloud, ``DROP`` -> forgotten."""
        a = self.active
        out = self.marginalize_points(a.flag == PointFlag.MARGINALIZE)
        self.drop_points(a.flag == PointFlag.DROP)
        return out

    def describe(self) -> dict:
        """Counts for logs and observers."""
        return {"keyframes": self.num_keyframes, "keyframe_ids": [int(self.keyframe_id_[s]) for s in self.order],
                "active_points": self.active.n, "immature_points": self.immature.n, "cloud_points": len(self.cloud)}


def _inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out

