"""The Gaussian map: the one owner of the Gaussian parameters, their gradients, Adam moments and statistics.

Layout (project-wide; docs/mapping.md): N Gaussians, each

=================  ================  =====================================================================
field              Warp buffer       meaning
=================  ================  =====================================================================
means              vec3 [N]          centre, world units
log_scales         vec3 [N]          log of the standard deviations along the local axes (scale = exp)
quats              vec4 [N]          rotation (w, x, y, z), not necessarily unit (normalised when used)
opacity_logits     float32 [N]       opacity = sigmoid(logit)
sh                 vec3 [N, K]       SH coefficients per RGB channel, K = (degree + 1)^2;
                                     RGB = max(0, 0.5 + 0.28209479177387814 * sh[:, 0] + higher bands)
=================  ================  =====================================================================

NumPy views of these have the shapes (N, 3), (N, 3), (N, 4), (N,), (N, K, 3) float32.

Buffers are preallocated to ``capacity`` rows (``means_`` etc., trailing underscore); the properties without the
underscore are views of the live rows ``[:n]``. Views and the :class:`~mgso_kernels.adam.GaussianParams` structs
returned by :attr:`GaussianMap.params`, :attr:`grads`, :attr:`exp_avg`, ... are valid until the next structural change
(:meth:`add`, :meth:`remove`, :meth:`clone`, :meth:`split`, :meth:`sort_spatially`, :meth:`reserve`, :meth:`clear`):
fetch them again after.

Who may change what (DSO's habit: the owner says it next to the field):

- parameters: :meth:`add`, :meth:`remove`, :meth:`clone`, :meth:`split`, :meth:`load`, :meth:`clear`,
  :meth:`reset_opacity` (opacity only) and :meth:`optimizer_step` (every live row). Nobody else writes them; the
  rasteriser reads them through :attr:`params`.
- gradients (:attr:`grads`): written by the rasteriser's backward, zeroed by :meth:`zero_grad` and by every structural
  change (they refer to the old rows), read by :meth:`optimizer_step`.
- Adam moments and per-Gaussian step counts: :meth:`optimizer_step`; structural changes move them with their rows and
  zero them for new rows; :meth:`reset_opacity` zeroes the opacity moments (as 3DGS and gsplat do).
- densification statistics (:attr:`stats`): :meth:`accumulate_stats` (or a rasteriser writing into :attr:`stats` in
  the same units), :meth:`reset_stats`; structural changes move them and zero them for new rows.
- ages: ``created_step`` is set by :meth:`add` / :meth:`clone` / :meth:`split` for the rows they create;
  ``stats.views_seen`` counts training views in which the Gaussian was visible and is never reset.
- anchors: ``anchor`` is the keyframe a Gaussian was seeded from (-1: none), set by :meth:`add`, inherited by clones
  and split children; :meth:`transform_anchored` moves the Gaussians of corrected keyframes by their Sim(3)
  (loop closure, docs/loop.md).

Nothing here grows the buffers implicitly: a full map raises :class:`MapFullError`; :meth:`reserve` grows it, between
iterations only (it reallocates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import warp as wp

from mgso.config import OptimConfig
from mgso.geometry import matrix_to_quat_wxyz, sim3_to_parts
from mgso_kernels import adam as kadam
from mgso_kernels import runtime

__all__ = [
    "SH_C0", "MapFullError", "GaussianArrays", "ActivatedGaussians", "FloatParams", "GaussianMap", "num_sh_coeffs",
    "sh_degree_from_coeffs", "means_learning_rate", "exposure_learning_rate", "scene_extent_from_cameras",
    "quat_wxyz_to_rotmat", "rgb_to_sh_dc", "spatial_order",
]

SH_C0 = 0.28209479177387814   # Y_0^0 = 1 / (2 sqrt(pi))

_BIAS_MODES = {"none": kadam.BIAS_NONE, "global": kadam.BIAS_GLOBAL, "per_gaussian": kadam.BIAS_PER_GAUSSIAN}


class MapFullError(RuntimeError):
    """The map has no room for the Gaussians asked for; call :meth:`GaussianMap.reserve` between iterations."""


def num_sh_coeffs(degree: int) -> int:
    if not 0 <= degree <= 4:
        raise ValueError(f"SH degree must be 0..4, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_coeffs(k: int) -> int:
    d = int(round(math.sqrt(k))) - 1
    if d < 0 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per channel is not (degree + 1)^2")
    return d


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """SH DC coefficients whose degree-0 colour is ``rgb`` (inverse of 0.5 + SH_C0 * dc)."""
    return ((np.asarray(rgb, dtype=np.float32) - 0.5) / SH_C0).astype(np.float32)


def quat_wxyz_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of a (4,) quaternion with (N, 4) ones, w x y z (the rotation of ``b`` then
    ``a``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=1)


def _expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
              delay_mult: float = 1.0) -> float:
    """3DGS's ``get_expon_lr_func``: log-linear from lr_init (step 0) to lr_final (max_steps), constant after; an
    optional warm-up multiplies by delay_mult + (1 - delay_mult) * sin(pi/2 * min(step / delay_steps, 1))."""
    if lr_init == lr_final or max_steps <= 0:
        lr = lr_init
    else:
        t = min(max(step / max_steps, 0.0), 1.0)
        if lr_init <= 0 or lr_final <= 0:
            lr = lr_init * (1 - t) + lr_final * t
        else:
            lr = math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)
    if delay_steps > 0:
        lr *= delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0.0), 1.0))
    return lr


def means_learning_rate(cfg: OptimConfig, step: int, scene_extent: float) -> float:
    """Learning rate of the means at ``step`` (0-based): 3DGS's exponential decay, times the scene extent."""
    return scene_extent * _expon_lr(step, cfg.lr_means_init, cfg.lr_means_final, cfg.lr_means_max_steps,
                                    cfg.lr_means_delay_steps, cfg.lr_means_delay_mult)


def exposure_learning_rate(cfg: OptimConfig, step: int) -> float:
    """Learning rate of per-keyframe exposures at ``step``: 3DGS's exposure schedule over lr_means_max_steps."""
    return _expon_lr(step, cfg.lr_exposure_init, cfg.lr_exposure_final, cfg.lr_means_max_steps)


def spatial_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """The permutation that sorts ``points`` (N, 3) along a Z-order (Morton) curve: each coordinate quantised to
    ``bits`` bits over the points' 1st-99th percentile box (points outside it clamp to its faces, non-finite ones to
    its low corner), the bits interleaved, a stable sort. Runs of neighbouring indices are then small boxes of
    space."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    p = np.where(np.isfinite(p), p, np.nan)
    lo, hi = np.nanpercentile(p, 1, axis=0), np.nanpercentile(p, 99, axis=0)
    lo, hi = np.nan_to_num(lo), np.nan_to_num(hi)
    top = (1 << bits) - 1
    q = np.nan_to_num((p - lo) / np.maximum(hi - lo, 1e-12) * top, nan=0.0)
    q = np.clip(q, 0, top).astype(np.uint64)
    code = np.zeros(len(p), np.uint64)
    for b in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + axis)
    return np.argsort(code, kind="stable")


def scene_extent_from_cameras(cam_centres: np.ndarray, margin: float = 1.1) -> float:
    """3DGS's ``cameras_extent``: ``margin`` x the largest distance of a camera centre from their centroid.

    With one camera (or cameras that have not moved) this is 0; a SLAM trainer should floor it (e.g. with the median
    scene depth) before using it for learning rates and size thresholds.
    """
    c = np.asarray(cam_centres, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        raise ValueError("scene_extent_from_cameras: no camera centres")
    return float(margin * np.linalg.norm(c - c.mean(axis=0), axis=1).max())


# ------------------------------------------------------------------------------------------- value types
@dataclass
class GaussianArrays:
    """The Gaussian parameters as NumPy float32 arrays, in the project-wide layout (see module doc)."""

    means: np.ndarray            # (N, 3) world
    log_scales: np.ndarray       # (N, 3)
    quats: np.ndarray            # (N, 4) w x y z, not necessarily unit
    opacity_logits: np.ndarray   # (N,)
    sh: np.ndarray               # (N, K, 3)

    def __post_init__(self):
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32).reshape(-1)
        sh = np.asarray(self.sh, dtype=np.float32)
        if sh.ndim == 2 and sh.shape[1:] == (3,):   # DC only
            sh = sh[:, None, :]
        self.sh = np.ascontiguousarray(sh)
        n = self.means.shape[0]
        for name, a, shape in (("means", self.means, (n, 3)), ("log_scales", self.log_scales, (n, 3)),
                               ("quats", self.quats, (n, 4)), ("opacity_logits", self.opacity_logits, (n,))):
            if a.shape != shape:
                raise ValueError(f"GaussianArrays.{name}: expected shape {shape}, got {a.shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianArrays.sh: expected shape ({n}, K, 3), got {self.sh.shape}")
        sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def n(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    def activated(self) -> "ActivatedGaussians":
        """Scales, unit quaternions, opacities and the degree-0 (view-independent) RGB."""
        q = self.quats.astype(np.float64)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(norm > 0, q / np.maximum(norm, 1e-30), np.array([1.0, 0, 0, 0]))
        return ActivatedGaussians(
            means=self.means.copy(), scales=np.exp(self.log_scales.astype(np.float64)).astype(np.float32),
            quats=q.astype(np.float32),
            opacities=(1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))).astype(np.float32),
            rgb=np.maximum(0.0, 0.5 + SH_C0 * self.sh[:, 0, :]).astype(np.float32))


@dataclass
class ActivatedGaussians:
    """Parameters after their activations (what a viewer or an evaluation wants)."""

    means: np.ndarray      # (N, 3) world
    scales: np.ndarray     # (N, 3) standard deviations, world units
    quats: np.ndarray      # (N, 4) unit, w x y z
    opacities: np.ndarray  # (N,) in (0, 1)
    rgb: np.ndarray        # (N, 3) degree-0 colour max(0, 0.5 + SH_C0 * dc); higher bands are view-dependent


@dataclass(frozen=True)
class FloatParams:
    """Zero-copy float32 views of a parameter set, for kernels that take plain float rows (``array2d(float)``)."""

    means: wp.array            # (n, 3) float32
    log_scales: wp.array       # (n, 3)
    quats: wp.array            # (n, 4) w x y z
    opacity_logits: wp.array   # (n,)
    sh: wp.array               # (n, K, 3)


# ------------------------------------------------------------------------------------------------- the map
def _alloc_params(capacity: int, k: int, device: str) -> kadam.GaussianParams:
    s = kadam.GaussianParams()
    s.means = wp.zeros(capacity, dtype=wp.vec3, device=device)
    s.log_scales = wp.zeros(capacity, dtype=wp.vec3, device=device)
    s.quats = wp.zeros(capacity, dtype=wp.vec4, device=device)
    s.opacity_logits = wp.zeros(capacity, dtype=wp.float32, device=device)
    s.sh = wp.zeros((capacity, k), dtype=wp.vec3, device=device)
    return s


def _alloc_stats(capacity: int, device: str) -> kadam.DensifyStats:
    s = kadam.DensifyStats()
    s.grad2d_sum = wp.zeros(capacity, dtype=wp.float32, device=device)
    s.absgrad2d_sum = wp.zeros(capacity, dtype=wp.float32, device=device)
    s.vis_count = wp.zeros(capacity, dtype=wp.int32, device=device)
    s.max_radius_px = wp.zeros(capacity, dtype=wp.float32, device=device)
    s.views_seen = wp.zeros(capacity, dtype=wp.int32, device=device)
    s.weight_max = wp.zeros(capacity, dtype=wp.float32, device=device)
    return s


_PARAM_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")
_STAT_FIELDS = ("grad2d_sum", "absgrad2d_sum", "vis_count", "max_radius_px", "views_seen", "weight_max")


def _slice_struct(full, fields: Sequence[str], n: int, cls):
    s = cls()
    for f in fields:
        setattr(s, f, getattr(full, f)[:n])
    return s


class GaussianMap:
    """Capacity-bounded struct-of-arrays store of Gaussians with their optimiser state (see module doc).

    ``capacity``: rows preallocated; ``sh_degree``: 0..3 (K = (degree+1)^2 coefficients per channel);
    ``device``: Warp device (default: the runtime's); ``optim``: Adam settings used by :meth:`optimizer_step`.
    ``scene_extent`` (world units, set by the trainer between iterations) scales the means learning rate and the
    strategy's size thresholds.
    """

    def __init__(self, capacity: int, sh_degree: int = 0, device: str | None = None,
                 optim: OptimConfig | None = None, scene_extent: float = 1.0):
        if capacity < 1:
            raise ValueError(f"GaussianMap capacity must be >= 1, got {capacity}")
        self.device = runtime.device_or_cpu(device)
        self.sh_degree = int(sh_degree)
        self.num_sh = num_sh_coeffs(self.sh_degree)
        self.optim = optim if optim is not None else OptimConfig()
        if self.optim.bias_correction not in _BIAS_MODES:
            raise ValueError(f"optim.bias_correction must be one of {sorted(_BIAS_MODES)}, got "
                             f"{self.optim.bias_correction!r}")
        self.scene_extent = float(scene_extent)
        self._n = 0
        self._live_views: dict[str, tuple] = {}   # ONLY changed by _live
        self._allocate(int(capacity))

    # ---------------------------------------------------------------------------------------- storage
    def _allocate(self, capacity: int) -> None:
        d, k = self.device, self.num_sh
        self._live_views.clear()   # the views of the old buffers would keep them alive
        self._capacity = capacity
        # ONLY changed by add/remove/clone/split/load/clear/reset_opacity/optimizer_step (see module doc).
        self.params_ = _alloc_params(capacity, k, d)
        # written by the rasteriser's backward; zeroed by zero_grad and structural changes.
        self.grads_ = _alloc_params(capacity, k, d)
        # ONLY changed by optimizer_step, structural changes and reset_opacity (opacity rows).
        self.exp_avg_ = _alloc_params(capacity, k, d)
        self.exp_avg_sq_ = _alloc_params(capacity, k, d)
        self.adam_steps_ = wp.zeros(capacity, dtype=wp.int32, device=d)      # updates received per Gaussian
        # ONLY changed by accumulate_stats (or the rasteriser, same units), reset_stats and structural changes.
        self.stats_ = _alloc_stats(capacity, d)
        # ONLY set by add/clone/split for the rows they create.
        self.created_step_ = wp.zeros(capacity, dtype=wp.int32, device=d)
        # ONLY set by add (clones and split children inherit their parent's): the keyframe a Gaussian was seeded from
        self.anchor_ = wp.full(capacity, -1, dtype=wp.int32, device=d)

    def _all_buffers(self):
        """(name, full buffer, kind) of every per-row buffer; kind: param / moment / stat / age."""
        out = []
        for f in _PARAM_FIELDS:
            out.append((f"params.{f}", getattr(self.params_, f), "param"))
            out.append((f"exp_avg.{f}", getattr(self.exp_avg_, f), "moment"))
            out.append((f"exp_avg_sq.{f}", getattr(self.exp_avg_sq_, f), "moment"))
        out.append(("adam_steps", self.adam_steps_, "moment"))
        for f in _STAT_FIELDS:
            out.append((f"stats.{f}", getattr(self.stats_, f), "stat" if f != "views_seen" else "age"))
        out.append(("created_step", self.created_step_, "age"))
        out.append(("anchor", self.anchor_, "anchor"))
        return out

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def n(self) -> int:
        """Number of live Gaussians."""
        return self._n

    def __len__(self) -> int:
        return self._n

    # live views ------------------------------------------------------------------------------------
    @property
    def means(self) -> wp.array:            # [n] vec3 world
        return self.params_.means[: self._n]

    @property
    def log_scales(self) -> wp.array:       # [n] vec3
        return self.params_.log_scales[: self._n]

    @property
    def quats(self) -> wp.array:            # [n] vec4 w x y z
        return self.params_.quats[: self._n]

    @property
    def opacity_logits(self) -> wp.array:   # [n] float32
        return self.params_.opacity_logits[: self._n]

    @property
    def sh(self) -> wp.array:               # [n, K] vec3
        return self.params_.sh[: self._n]

    def _live(self, name: str, full, fields: Sequence[str], build):
        """``build()``, a view of the live rows of the buffers ``full`` (a struct of capacity-long arrays), made again
        only when the rows or the buffers changed: a view is a few Warp arrays, and a training step asks for seven
        (with the rasteriser's buffers' views, a sixth of its Python at 160x120: docs/rasteriser.md, "Python between
        the kernels"). Keyed by the row count and the buffers' ids; the view keeps its buffers alive (a slice holds its
        parent), so an id in the key is never that of another buffer. Views are read-only to their users."""
        key = (self._n, *[id(getattr(full, f)) for f in fields])
        hit = self._live_views.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        value = build()
        self._live_views[name] = (key, value)
        return value

    @property
    def params(self) -> kadam.GaussianParams:
        """Device-side view of the live parameters for the rasteriser (valid until the next structural change)."""
        return self._live("params", self.params_, _PARAM_FIELDS,
                          lambda: _slice_struct(self.params_, _PARAM_FIELDS, self._n, kadam.GaussianParams))

    @property
    def grads(self) -> kadam.GaussianParams:
        """Gradient buffers of the live rows: the rasteriser's backward writes dL/d(parameter) here."""
        return self._live("grads", self.grads_, _PARAM_FIELDS,
                          lambda: _slice_struct(self.grads_, _PARAM_FIELDS, self._n, kadam.GaussianParams))

    def float_params(self) -> FloatParams:
        """The live parameters as float32 (n, 3) / (n, 4) / (n,) / (n, K, 3) views (same memory as :attr:`params`)."""
        return self._live("float_params", self.params_, _PARAM_FIELDS, lambda: FloatParams(
            **{f: kadam.float_view(getattr(self.params_, f)[: self._n]) for f in _PARAM_FIELDS}))

    def float_grads(self) -> FloatParams:
        """The live gradient buffers as float32 views (same memory as :attr:`grads`), for the rasteriser's backward."""
        return self._live("float_grads", self.grads_, _PARAM_FIELDS, lambda: FloatParams(
            **{f: kadam.float_view(getattr(self.grads_, f)[: self._n]) for f in _PARAM_FIELDS}))

    @property
    def exp_avg(self) -> kadam.GaussianParams:
        return self._live("exp_avg", self.exp_avg_, _PARAM_FIELDS,
                          lambda: _slice_struct(self.exp_avg_, _PARAM_FIELDS, self._n, kadam.GaussianParams))

    @property
    def exp_avg_sq(self) -> kadam.GaussianParams:
        return self._live("exp_avg_sq", self.exp_avg_sq_, _PARAM_FIELDS,
                          lambda: _slice_struct(self.exp_avg_sq_, _PARAM_FIELDS, self._n, kadam.GaussianParams))

    @property
    def stats(self) -> kadam.DensifyStats:
        """Densification statistics of the live rows (units: :mod:`mgso_kernels.adam`)."""
        return self._live("stats", self.stats_, _STAT_FIELDS,
                          lambda: _slice_struct(self.stats_, _STAT_FIELDS, self._n, kadam.DensifyStats))

    @property
    def adam_steps(self) -> wp.array:       # [n] int32 Adam updates received
        return self.adam_steps_[: self._n]

    @property
    def created_step(self) -> wp.array:     # [n] int32 training step at which the row was created
        return self.created_step_[: self._n]

    @property
    def anchor(self) -> wp.array:           # [n] int32 keyframe the Gaussian was seeded from (-1: none)
        return self.anchor_[: self._n]

    # ------------------------------------------------------------------------------------- helpers
    def _upload(self, buf: wp.array, lo: int, values: np.ndarray) -> None:
        hi = lo + len(values)
        if hi > lo:
            buf[lo:hi].assign(np.ascontiguousarray(values))

    def _zero_rows(self, buf: wp.array, lo: int, hi: int) -> None:
        if hi > lo:
            buf[lo:hi].zero_()

    def _fill_rows(self, buf: wp.array, lo: int, hi: int, value) -> None:
        if hi > lo:
            buf[lo:hi].fill_(value)

    def _check_room(self, extra: int, what: str) -> None:
        if self._n + extra > self._capacity:
            raise MapFullError(f"GaussianMap is full: {what} needs {extra} more rows, {self._n} of "
                               f"{self._capacity} are used; call reserve() between iterations (mapping.capacity)")

    def _rebuild(self, index: np.ndarray, fresh_from: int, step: int) -> None:
        """Rows become ``old[index]``; rows ``fresh_from:`` are new: moments, stats and ages start afresh."""
        index = np.ascontiguousarray(index, dtype=np.int32)
        m = len(index)
        if m > self._capacity:
            raise MapFullError(f"GaussianMap is full: the change needs {m} rows, capacity {self._capacity}; call "
                               "reserve() between iterations")
        if m:
            widx = wp.array(index, dtype=wp.int32, device=self.device)
            for _, buf, _kind in self._all_buffers():
                tmp = wp.empty((m,) + tuple(buf.shape[1:]), dtype=buf.dtype, device=self.device)
                kadam.gather(buf[: self._n], widx, tmp, device=self.device)
                buf[:m].assign(tmp)
        for name, buf, kind in self._all_buffers():
            if kind in ("moment", "stat") or name == "stats.views_seen":
                self._zero_rows(buf, fresh_from, m)
        self._fill_rows(self.created_step_, fresh_from, m, int(step))
        self._n = m
        self.zero_grad()

    # ------------------------------------------------------------------------------------ operations
    def add(self, means, log_scales, quats, opacity_logits, sh, step: int = 0, anchor=-1) -> np.ndarray:
        """Append Gaussians (moments, stats and step counts zero; ``created_step`` = ``step``).

        Arrays: means (M, 3), log_scales (M, 3), quats (M, 4) w x y z, opacity_logits (M,), sh (M, K, 3) with this
        map's K, or (M, 3) for the DC coefficients only (higher bands zero). ``anchor``: the keyframe id they were
        seeded from, one for all or (M,) (-1: none). Returns the new row indices.
        """
        means = np.asarray(means, dtype=np.float32).reshape(-1, 3)
        m = len(means)
        arrays = GaussianArrays(means, log_scales, quats, opacity_logits,
                                self._expand_sh(np.asarray(sh, dtype=np.float32), m))
        bad = [f for f in _PARAM_FIELDS if not np.all(np.isfinite(getattr(arrays, f)))]
        if bad:
            raise ValueError(f"GaussianMap.add: non-finite values in {bad}")
        self._check_room(m, f"add({m})")
        lo = self._n
        for f in _PARAM_FIELDS:
            self._upload(getattr(self.params_, f), lo, getattr(arrays, f))
        for _, buf, kind in self._all_buffers():
            if kind not in ("param", "anchor"):
                self._zero_rows(buf, lo, lo + m)
        self._fill_rows(self.created_step_, lo, lo + m, int(step))
        anchors = np.asarray(anchor, dtype=np.int64)
        if anchors.ndim == 0:
            self._fill_rows(self.anchor_, lo, lo + m, int(anchors))
        elif anchors.shape == (m,):
            self._upload(self.anchor_, lo, anchors.astype(np.int32))
        else:
            raise ValueError(f"GaussianMap.add: anchor must be one id or ({m},), got shape {anchors.shape}")
        for f in _PARAM_FIELDS:
            self._zero_rows(getattr(self.grads_, f), lo, lo + m)
        self._n = lo + m
        return np.arange(lo, lo + m)

    def _expand_sh(self, sh: np.ndarray, m: int) -> np.ndarray:
        k = self.num_sh
        if sh.shape == (m, 3):
            out = np.zeros((m, k, 3), np.float32)
            out[:, 0] = sh
            return out
        if sh.shape != (m, k, 3):
            raise ValueError(f"GaussianMap.add: sh must be ({m}, {k}, 3) for SH degree {self.sh_degree} or ({m}, 3) "
                             f"DC only, got {sh.shape}")
        return sh

    def _mask(self, mask, what: str) -> np.ndarray:
        if isinstance(mask, wp.array):
            mask = mask.numpy()
        mask = np.asarray(mask)
        if mask.shape != (self._n,):
            raise ValueError(f"GaussianMap.{what}: mask must have shape ({self._n},), got {mask.shape}")
        return mask.astype(bool)

    def remove(self, mask) -> int:
        """Remove the rows where ``mask`` (n,) is true; survivors keep their order. Returns the number removed."""
        mask = self._mask(mask, "remove")
        keep = np.flatnonzero(~mask)
        removed = self._n - len(keep)
        if removed:
            self._rebuild(keep, len(keep), 0)
        return removed

    def clone(self, mask, step: int = 0) -> int:
        """Append a copy of every row where ``mask`` is true (3DGS ``densify_and_clone``): same parameters, zero
        moments and statistics, ``created_step`` = ``step``. Originals keep their state. Returns the number cloned."""
        mask = self._mask(mask, "clone")
        sel = np.flatnonzero(mask)
        if len(sel) == 0:
            return 0
        self._check_room(len(sel), f"clone({len(sel)})")
        n = self._n
        self._rebuild(np.concatenate([np.arange(n), sel]), n, step)
        return len(sel)

    def split(self, mask, children: int = 2, step: int = 0, rng: np.random.Generator | None = None,
              scale_factor: float = 0.8) -> int:
        """Replace every row where ``mask`` is true by ``children`` new Gaussians (3DGS ``densify_and_split``).

        Rules (graphdeco 3DGS, gsplat ``ops.split``): each child's mean is the parent's plus R(q) (s * z) with
        z ~ N(0, I) (a sample from the parent Gaussian); log-scales are log(s / (scale_factor * children)) (s / 1.6
        for two); quaternion, opacity and SH are copied; moments and statistics start at zero; ``created_step`` =
        ``step``. Survivors keep their order and come first; children are appended, all first children then all
        second ones. Returns the number of parents split.
        """
        mask = self._mask(mask, "split")
        sel = np.flatnonzero(mask)
        if len(sel) == 0:
            return 0
        if children < 1:
            raise ValueError(f"GaussianMap.split: children must be >= 1, got {children}")
        self._check_room(len(sel) * (children - 1), f"split({len(sel)} x {children})")
        rng = rng if rng is not None else np.random.default_rng()
        means = self.means.numpy()[sel].astype(np.float64)
        scales = np.exp(self.log_scales.numpy()[sel].astype(np.float64))
        R = quat_wxyz_to_rotmat(self.quats.numpy()[sel])
        z = rng.standard_normal((children, len(sel), 3))
        new_means = (means[None] + np.einsum("nij,cnj->cni", R, scales[None] * z)).reshape(-1, 3)
        new_log_scales = np.tile(np.log(scales / (scale_factor * children)), (children, 1))
        keep = np.flatnonzero(~mask)
        self._rebuild(np.concatenate([keep, np.tile(sel, children)]), len(keep), step)
        self._upload(self.params_.means, len(keep), new_means.astype(np.float32))
        self._upload(self.params_.log_scales, len(keep), new_log_scales.astype(np.float32))
        return len(sel)

    def transform_anchored(self, transforms) -> int:
        """Move the Gaussians of corrected keyframes: ``transforms`` maps keyframe id -> 4x4 Sim(3) ``[[s R, t],
        [0, 1]]`` (``X' = s R X + t``, world to corrected world); every Gaussian anchored to that keyframe gets its
        mean mapped, its rotation turned by R and its scales multiplied by s (a rigid map of a Sim(3)'s shape).
        Gaussians of other keyframes (and unanchored ones) stay. Adam moments stay too: a loop correction is a few
        degrees and a few percent of scale, and the moments follow within a few steps. Returns the rows moved."""
        if self._n == 0 or not transforms:
            return 0
        anchors = self.anchor.numpy()
        means = self.means.numpy().astype(np.float64)
        log_scales = self.log_scales.numpy().astype(np.float64)
        quats = self.quats.numpy().astype(np.float64)
        moved = 0
        for kid, S in transforms.items():
            rows = np.flatnonzero(anchors == int(kid))
            if len(rows) == 0:
                continue
            R, t, s = sim3_to_parts(S)
            if not (np.isfinite(s) and s > 0):
                raise ValueError(f"GaussianMap.transform_anchored: keyframe {kid}: not a Sim(3) (det {s ** 3:g})")
            means[rows] = s * (means[rows] @ R.T) + t
            log_scales[rows] += math.log(s)
            quats[rows] = _quat_mul(matrix_to_quat_wxyz(R), quats[rows])
            moved += len(rows)
        if moved:
            self.means.assign(means.astype(np.float32))
            self.log_scales.assign(log_scales.astype(np.float32))
            self.quats.assign(quats.astype(np.float32))
        return moved

    def sort_spatially(self) -> bool:
        """Put the rows in the Z-order (Morton order) of their means (:func:`spatial_order`), every row's state with
        it; returns whether the order changed. A view then culls whole runs of neighbouring rows: the CPU's
        projection, binning and projection-backward blocks pass over a group of 16 rows that the view does not show
        (docs/rasteriser.md), and a tile's Gaussians lie closer together in memory. The map's content is the same;
        renders differ only where two Gaussians at exactly the same depth share a tile (the tile lists keep index
        order for ties)."""
        n = self._n
        if n < 2:
            return False
        order = spatial_order(self.means.numpy())
        if np.array_equal(order, np.arange(n)):
            return False
        self._rebuild(order, n, 0)
        return True

    def reset_opacity(self, max_value: float) -> None:
        """Clamp every opacity to at most ``max_value`` (in (0, 1)) and zero the opacity moments (3DGS)."""
        if not 0.0 < max_value < 1.0:
            raise ValueError(f"reset_opacity: max_value must be in (0, 1), got {max_value}")
        cap = math.log(max_value / (1.0 - max_value))
        logits = self.opacity_logits.numpy()
        new = np.minimum(logits, np.float32(cap))
        self.opacity_logits.assign(new)
        self.exp_avg_.opacity_logits[: self._n].zero_()
        self.exp_avg_sq_.opacity_logits[: self._n].zero_()

    def reserve(self, capacity: int) -> None:
        """Grow (or shrink to no less than n) the buffers to ``capacity`` rows, keeping every live row's state.
        Reallocates: call it between iterations, and fetch views/structs again after."""
        if capacity < self._n:
            raise ValueError(f"reserve({capacity}): the map holds {self._n} Gaussians")
        if capacity == self._capacity:
            return
        old = self._all_buffers()
        old_grads = [getattr(self.grads_, f) for f in _PARAM_FIELDS]
        self._allocate(int(capacity))
        n = self._n
        for (_, src, _), (_, dst, _) in zip(old, self._all_buffers()):
            if n:
                dst[:n].assign(src[:n])
        for src, f in zip(old_grads, _PARAM_FIELDS):
            if n:
                getattr(self.grads_, f)[:n].assign(src[:n])

    def clear(self) -> None:
        """Remove every Gaussian (capacity unchanged)."""
        self._n = 0

    def load(self, arrays: GaussianArrays, step: int = 0) -> None:
        """Replace the content by ``arrays`` (e.g. read from a PLY); optimiser state starts afresh."""
        if arrays.sh.shape[1] != self.num_sh:
            raise ValueError(f"GaussianMap.load: arrays have SH degree {arrays.sh_degree}, the map "
                             f"{self.sh_degree}")
        self.clear()
        self.add(arrays.means, arrays.log_scales, arrays.quats, arrays.opacity_logits, arrays.sh, step=step)

    @classmethod
    def from_arrays(cls, arrays: GaussianArrays, capacity: int | None = None, device: str | None = None,
                    optim: OptimConfig | None = None, scene_extent: float = 1.0) -> "GaussianMap":
        gm = cls(capacity if capacity is not None else max(1, arrays.n), arrays.sh_degree, device, optim,
                 scene_extent)
        gm.load(arrays)
        return gm

    # ------------------------------------------------------------------------------------- training
    def zero_grad(self) -> None:
        """Zero the gradient buffers of the live rows (before the rasteriser's backward writes them)."""
        for f in _PARAM_FIELDS:
            self._zero_rows(getattr(self.grads_, f), 0, self._n)

    def reset_stats(self) -> None:
        """Zero the densification statistics (not ``views_seen``, which is an age)."""
        for f in ("grad2d_sum", "absgrad2d_sum", "vis_count", "max_radius_px", "weight_max"):
            self._zero_rows(getattr(self.stats_, f), 0, self._n)

    def accumulate_stats(self, v_means2d: wp.array, radii: wp.array, width: int, height: int,
                         v_means2d_abs: wp.array | None = None, weights: wp.array | None = None,
                         weight_scale: float = 1.0) -> None:
        """Add one training view's statistics: ``v_means2d`` [n] vec2 dL/d(projected mean) in pixels, ``radii``
        [n] float32 or int32 screen radius in pixels (0 = not drawn), optional AbsGS ``v_means2d_abs`` [n] vec2
        pixels, optional ``weights`` [n] float32 blending weights summed over the view's pixels (``stats.weight_max``
        keeps the largest, times ``weight_scale``). Converts to NDC units (x W/2, H/2) as 3DGS measures its
        threshold."""
        kadam.accumulate_stats(self.stats, v_means2d, radii, width, height, v_means2d_abs, device=self.device,
                               weights=weights, weight_scale=weight_scale)

    def learning_rates(self, step: int) -> kadam.AdamRates:
        """Per-group learning rates at ``step`` (0-based) from :attr:`optim` and :attr:`scene_extent`."""
        o = self.optim
        return kadam.AdamRates(means=means_learning_rate(o, step, self.scene_extent), log_scales=o.lr_log_scales,
                               quats=o.lr_quats, opacity_logits=o.lr_opacity, sh_dc=o.lr_sh_dc,
                               sh_rest=o.lr_sh_rest)

    def optimizer_step(self, step: int, visible: wp.array | None = None) -> kadam.AdamRates:
        """One Adam step of every live Gaussian from :attr:`grads` (``step``: 0-based training step).

        With ``optim.sparse``, only Gaussians with ``visible[i] != 0`` ([n] uint8, e.g. radius > 0 in this view) are
        updated, or, when ``visible`` is None, those with a non-zero gradient. Returns the rates used.
        """
        rates = self.learning_rates(step)
        o = self.optim
        if visible is not None and (visible.dtype != wp.uint8 or visible.shape[0] != self._n):
            raise ValueError(f"optimizer_step: visible must be [{self._n}] uint8, got {visible.dtype.__name__} "
                             f"{visible.shape}")
        hp = kadam.make_hyper(rates, beta1=o.beta1, beta2=o.beta2, eps=o.eps,
                              bias_correction=_BIAS_MODES[o.bias_correction], global_step=step + 1,
                              sparse=o.sparse, use_visible=visible is not None)
        kadam.adam_step(self.params, self.grads, self.exp_avg, self.exp_avg_sq, self.adam_steps, hp,
                        visible=visible, device=self.device)
        return rates

    # --------------------------------------------------------------------------------------- export
    def to_numpy(self) -> GaussianArrays:
        """A NumPy copy of the live parameters."""
        return GaussianArrays(*(np.array(getattr(self, f).numpy(), copy=True) for f in _PARAM_FIELDS))

    def activated(self) -> ActivatedGaussians:
        """Scales, unit quaternions, opacities and degree-0 RGB of the live Gaussians (NumPy)."""
        return self.to_numpy().activated()

    def state_numpy(self) -> dict[str, np.ndarray]:
        """Copies of every per-row buffer (params, moments, steps, stats, ages) of the live rows, keyed by name."""
        return {name: np.array(buf[: self._n].numpy(), copy=True) for name, buf, _ in self._all_buffers()}

    def __repr__(self) -> str:
        return (f"GaussianMap(n={self._n}, capacity={self._capacity}, sh_degree={self.sh_degree}, "
                f"device={self.device!r}, scene_extent={self.scene_extent:g})")
