"""Tile-sorted 3D Gaussian Splatting rasteriser in Warp, with a hand-written backward pass.

One code path for the CPU (blending threads split over the cores) and CUDA. Use :class:`Rasterizer`:

    from mgso_kernels import runtime
    from mgso_kernels.splat import Rasterizer, make_camera

    device = runtime.init("cpu")
    rast = Rasterizer(device)
    cam = make_camera(fx, fy, cx, cy, width, height, world_to_cam)
    out = rast.forward(means, log_scales, quats, opacity_logits, sh, cam, background=(0, 0, 0))
    grads = rast.backward(out, v_rgb, v_depth=None, v_alpha=None)

Parameters (the Gaussian map's layout; NumPy or Warp arrays on the rasteriser's device):

- ``means``          (N, 3) float32, world coordinates
- ``log_scales``     (N, 3) float32, log of the standard deviations (scale = exp)
- ``quats``          (N, 4) float32, rotation quaternion **w, x, y, z**, any non-zero norm (normalised inside; the
  gradient flows through the normalisation)
- ``opacity_logits`` (N,)   float32, opacity = sigmoid(logit)
- ``sh``             (N, K, 3) float32, SH coefficients, K = (degree + 1)^2; colour =
  ``max(0, 0.5 + sum_k SH_k(dir) sh[:, k])``, dir = unit vector from the camera centre to the mean

Warp arrays of ``wp.vec3`` (N,) / ``wp.vec4`` (N,) are accepted for means / scales / quats too (viewed, not copied).

Conventions: camera x right, y down, z forward; pixel (row v, col u) samples the image plane at (u, v) (pixel
centres at integer coordinates); ``v_pose`` is the gradient w.r.t. ``delta`` in
``world_to_cam <- exp(delta) @ world_to_cam``, ``delta = (v, w)`` translation first (``mgso.geometry.se3_exp``).
See ``docs/rasteriser.md``.

**Buffers.** A :class:`Rasterizer` owns capacity-bounded buffers (per Gaussian, per (tile, Gaussian) pair, per
pixel) that grow geometrically (x1.5) when a frame needs more and are reused otherwise. Everything a
:class:`RenderOutput` or :class:`Gradients` holds is a view of those buffers: valid until the next call of
``forward`` / ``render_alpha`` (for render outputs) or ``backward`` (for gradients) on the same rasteriser. Copy
what you keep (``wp.clone``); use one rasteriser per thread. ``backward`` refuses an output from an earlier frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import warp as wp

from .. import runtime
from . import bin as _bin
from . import common as _common
from . import project as _project
from . import raster as _raster
from . import raster_bwd as _raster_bwd
from . import sh as _sh
from ._checks import as_float_array
from .camera import TILE_SIZE, Camera, camera_centre, make_camera

__all__ = ["Rasterizer", "RenderOutput", "AlphaOutput", "Gradients", "Camera", "make_camera", "camera_centre",
           "TILE_SIZE"]

_GROWTH = 1.5


@dataclass
class RenderOutput:
    """What :meth:`Rasterizer.forward` returns. Image arrays are Warp float32 arrays on the rasteriser's device.

    ``rgb`` (H, W, 3) in [0, 1]-ish units of the SH colours, background blended in with ``T_final``;
    ``depth`` (H, W): ``sum_i w_i z_i`` (camera z, **not** normalised: ``depth / alpha`` is the expected depth of
    the visible surface where ``alpha > 0``); ``alpha`` (H, W) = ``1 - T_final``; ``depth``, ``alpha``, ``T_final``
    and ``n_contrib`` are None after a ``forward(..., rgb_only=True)`` on the CPU.
    Per Gaussian (N,): ``radii`` int32 3-sigma screen radius in pixels (0 = culled / not visible);
    ``means2d`` (N, 2) pixels; ``depths`` (N,) camera z; ``tiles_touched`` (N,) int32.
    ``n_pairs``: number of (tile, Gaussian) pairs blended.
    """

    rgb: wp.array | None
    depth: wp.array | None
    alpha: wp.array | None
    radii: wp.array
    means2d: wp.array
    depths: wp.array
    tiles_touched: wp.array
    n_pairs: int
    camera: Camera
    background: tuple[float, float, float]
    num_bases: int
    # saved for the backward pass (views of the rasteriser's buffers)
    T_final: wp.array | None = field(default=None, repr=False)
    n_contrib: wp.array | None = field(default=None, repr=False)
    params: tuple = field(default=(), repr=False)
    generation: int = field(default=-1, repr=False)

    @property
    def num_visible(self) -> int:
        return int(np.count_nonzero(self.radii.numpy()))


@dataclass
class AlphaOutput:
    """What :meth:`Rasterizer.render_alpha` returns: ``alpha`` (H, W) float32 accumulated opacity (``1 - alpha`` is
    the transmittance; same rules as the full render), ``radii`` (N,) int32 3-sigma screen radius (0 = culled, i.e.
    not visible in this view), ``n_pairs`` (tile, Gaussian) pairs blended."""

    alpha: wp.array
    radii: wp.array
    n_pairs: int
    depth: wp.array | None = None   # (H, W) accumulated depth sum w z, with ``render_alpha(with_depth=True)``


@dataclass
class Gradients:
    """What :meth:`Rasterizer.backward` returns: float32 Warp arrays in the parameters' layout.

    ``v_means`` (N, 3), ``v_log_scales`` (N, 3), ``v_quats`` (N, 4), ``v_opacity_logits`` (N,), ``v_sh`` (N, K, 3)
    (zero above the SH degree used), ``v_pose`` (6,) for ``world_to_cam <- exp(delta) @ world_to_cam``,
    delta = (v, w). Screen space, for densification: ``v_means2d`` (N, 2) d loss / d mean2d in pixels,
    ``absgrad`` (N, 2) sum over pixels of |per-pixel d loss / d mean2d| (AbsGS), ``radii`` (N,) int32 (0 = not
    visible in this view). ``weights`` (N,): not a gradient but the sum over the view's pixels of the Gaussian's
    blending weight ``w = alpha T`` (how many pixels' worth of the render it makes; zero for one hidden behind opaque
    Gaussians in every pixel, or fainter than 1/255 in all; ``mgso_kernels.adam.accumulate_stats`` keeps its largest).
    """

    v_means: wp.array
    v_log_scales: wp.array
    v_quats: wp.array
    v_opacity_logits: wp.array
    v_sh: wp.array
    v_pose: wp.array
    v_means2d: wp.array
    absgrad: wp.array
    radii: wp.array
    weights: wp.array | None = None


class _Buffer:
    """One capacity-bounded buffer: ``full`` holds ``capacity`` rows; ``view(n)`` is the live part."""

    def __init__(self, dtype, tail: tuple[int, ...] = ()):
        self.dtype = dtype
        self.tail = tail
        self.full: wp.array | None = None
        self.capacity = 0
        self._view: tuple[int, wp.array | None, wp.array | None] = (-1, None, None)   # (n, full, full[:n])

    def ensure(self, n: int, device: str, exact: bool = False) -> bool:
        """Make room for ``n`` rows; returns True when it had to (re)allocate."""
        if self.full is not None and n <= self.capacity:
            return False
        cap = n if exact else max(n, int(math.ceil(self.capacity * _GROWTH)), 64)
        self.full = wp.empty((cap, *self.tail) if self.tail else cap, dtype=self.dtype, device=device)
        self.capacity = cap
        return True

    def view(self, n: int) -> wp.array:
        """``full[:n]``, the same array object while ``n`` and ``full`` stay (a slice costs a few microseconds, and a
        training step takes about thirty)."""
        m, full, view = self._view
        if m != n or full is not self.full:
            view = self.full[:n]
            self._view = (n, self.full, view)
        return view


class Rasterizer:
    """Workspace + entry points of the rasteriser (forward, alpha-only forward, backward).

    ``device``: Warp device name (``None``: the CPU). ``eps2d``: low-pass
    dilation of the 2D covariance (px^2, 3DGS's 0.3). ``antialiased``: also multiply each opacity by
    ``sqrt(det(J Sigma J^T) / det(J Sigma J^T + eps2d I))`` (Mip-Splatting's compensation, gsplat's ``antialiased`` mode);
    off by default, as in the original 3DGS. ``pixels_per_thread``: pixels a blending thread shades: 256 = a whole
    16x16 tile with the 16 pixels of a row in SIMD lanes (:mod:`~mgso_kernels.splat.raster_tile`, the CPU default),
    or 1, 2, 4, 8, 16 pixels of a tile row (:mod:`~mgso_kernels.splat.raster`; 1 is the CUDA default). ``threads``: CPU
    threads for split launches (``None``: the runtime's setting); ``min_chunk``: fewest threads a CPU chunk gets (a
    launch smaller than two chunks stays on one core). ``profile=True`` synchronises after each stage
    and records seconds per stage in :attr:`timings` (for ``profiles/splat_raster.py``; slows the pipeline a little).
    """

    def __init__(self, device: str | None = None, *, eps2d: float = 0.3, antialiased: bool = False,
                 pixels_per_thread: int | None = None, threads: int | None = None, min_chunk: int = 4096,
                 profile: bool = False):
        self.device = runtime.device_or_cpu(device)
        self.device_is_cpu = wp.get_device(self.device).is_cpu
        self.eps2d = float(eps2d)
        self.antialiased = bool(antialiased)
        self.threads = threads
        self._split = {"threads": threads, "min_chunk": int(min_chunk)}
        if pixels_per_thread is None:
            pixels_per_thread = TILE_SIZE * TILE_SIZE if self.device_is_cpu else 1
        if pixels_per_thread not in _raster.SEGMENT_WIDTHS:
            raise ValueError(f"pixels_per_thread must be one of {_raster.SEGMENT_WIDTHS}, got {pixels_per_thread}")
        self.pixels_per_thread = int(pixels_per_thread)
        self.profile = profile
        self.timings: dict[str, float] = {}
        self._generation = 0
        self._last_backward_n = 0
        # per Gaussian (capacity N); ``tiles_touched_`` and ``pair_offsets_`` hold N + 1 (the scan's total at N)
        self.means2d_ = _Buffer(wp.vec2)
        self.conics_ = _Buffer(wp.vec3)
        self.depths_ = _Buffer(wp.float32)
        self.opacities_ = _Buffer(wp.float32)
        self.radii_ = _Buffer(wp.int32)
        self.splat_g_ = _Buffer(_common.vec8)  # per Gaussian blending data
        self.rgbz_g_ = _Buffer(wp.vec4)  # per Gaussian colour + depth
        self.tiles_touched_ = _Buffer(wp.int32)
        self.pair_offsets_ = _Buffer(wp.int32)
        # per (tile, Gaussian) pair (capacity M; keys and slots 2M for the radix sort)
        self.keys_ = _Buffer(wp.int64)    # after binning: sorted on CUDA; on the CPU as emitted (only slots_ sorted)
        self.slots_ = _Buffer(wp.int32)
        self.sort_scratch_ = _Buffer(wp.int32)   # the CPU's sort from the Gaussians' side (bin.sort_pairs_and_ranges)
        self.bin_cache_ = _Buffer(wp.int32)   # CPU: the count's tile ranges kept for the emit (4 ints a Gaussian)
        self.pair_gauss_ = _Buffer(wp.int32)
        self.splats_ = _Buffer(_common.vec8)
        self.splat_rgbz_ = _Buffer(wp.vec4)
        self.pair_grads_ = _Buffer(_common.vec16)
        # per tile
        self.ranges_ = _Buffer(wp.int32, (2,))
        # per pixel (exact size; reallocated only when the resolution changes)
        self._image_shape: tuple[int, int] | None = None
        self._images: dict[str, wp.array] = {}
        # backward, per Gaussian
        self.v_means2d_ = _Buffer(wp.vec2)
        self.v_conics_ = _Buffer(wp.vec3)
        self.v_opacities_ = _Buffer(wp.float32)
        self.v_colors_ = _Buffer(wp.vec3)
        self.v_depths_ = _Buffer(wp.float32)
        self.absgrad_ = _Buffer(wp.vec2)
        self.weights_ = _Buffer(wp.float32)
        self.v_means_ = _Buffer(wp.float32, (3,))
        self.v_log_scales_ = _Buffer(wp.float32, (3,))
        self.v_quats_ = _Buffer(wp.float32, (4,))
        self.v_opacity_logits_ = _Buffer(wp.float32)
        self.v_sh_: _Buffer | None = None
        self.v_pose_partial_ = _Buffer(_common.vec6)
        self.pose_blocks_ = _Buffer(_project.vec6d)
        self.v_pose = wp.zeros(6, dtype=wp.float32, device=self.device)
        self.reallocations = 0  # how many times a buffer grew (steady state: constant)

    # ----------------------------------------------------------------------------------------------- helpers
    def _stage(self, name: str, t0: float) -> float:
        if not self.profile:
            return t0
        wp.synchronize_device(self.device)
        t = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + (t - t0)
        return t

    def _ensure(self, buf: _Buffer, n: int) -> None:
        if buf.ensure(n, self.device):
            self.reallocations += 1

    def _image(self, name: str, H: int, W: int) -> wp.array:
        if self._image_shape != (H, W):
            self._images = {}
            self._image_shape = (H, W)
        if name not in self._images:
            shape, dt = {"rgb": ((H, W, 3), wp.float32), "n_contrib": ((H, W), wp.int32)}.get(
                name, ((H, W), wp.float32))
            self._images[name] = wp.zeros(shape, dtype=dt, device=self.device)
            self.reallocations += 1
        return self._images[name]

    def _params(self, means, log_scales, quats, opacity_logits, sh):
        d = self.device
        means = as_float_array(means, "means", (3,), d)
        n = means.shape[0]
        log_scales = as_float_array(log_scales, "log_scales", (3,), d, n)
        quats = as_float_array(quats, "quats", (4,), d, n)
        opacity_logits = as_float_array(opacity_logits, "opacity_logits", (), d, n)
        if sh is not None:
            sh = as_float_array(sh, "sh", (-1, 3), d, n)
            if sh.shape[1] not in (1, 4, 9, 16):
                raise ValueError(f"sh: expected (N, K, 3) with K = (degree + 1)^2 in (1, 4, 9, 16), got K = "
                                 f"{sh.shape[1]}")
        return means, log_scales, quats, opacity_logits, sh

    def _into_arrays(self, into, n: int, k: int):
        from ._checks import check_array

        out = []
        for name, shape in (("means", (n, 3)), ("log_scales", (n, 3)), ("quats", (n, 4)), ("opacity_logits", (n,)),
                            ("sh", (n, k, 3))):
            a = getattr(into, name, None)
            if a is None:
                raise TypeError(f"backward(into=...): {type(into).__name__} has no array '{name}'")
            out.append(check_array(a, f"into.{name}", wp.float32, shape, self.device))
        return out

    def _check_camera(self, camera) -> None:
        if not isinstance(camera, Camera.cls):
            raise TypeError(f"camera: expected mgso_kernels.splat.Camera (use make_camera), got "
                            f"{type(camera).__name__}")

    # ------------------------------------------------------------------------------------- shared front end
    def _project_and_bin(self, means, log_scales, quats, opacity_logits, camera: Camera) -> int:
        """Projection + binning + sort + tile ranges; returns the number of pairs."""
        dev, sp = self.device, self._split
        n = means.shape[0]
        for buf in (self.means2d_, self.conics_, self.depths_, self.opacities_, self.radii_, self.splat_g_,
                    self.rgbz_g_):
            self._ensure(buf, n)
        self._ensure(self.tiles_touched_, n + 1)
        self._ensure(self.pair_offsets_, n + 1)
        t = time.perf_counter()
        means2d, conics = self.means2d_.view(n), self.conics_.view(n)
        depths, opac, radii = self.depths_.view(n), self.opacities_.view(n), self.radii_.view(n)
        splat_g = self.splat_g_.view(n)
        _project.launch_project(means, log_scales, quats, opacity_logits, camera, self.eps2d, self.antialiased,
                                means2d, conics, depths, opac, radii, splat_g, dev, **sp)
        t = self._stage("project", t)
        touched = self.tiles_touched_.view(n + 1)
        offsets = self.pair_offsets_.view(n + 1)
        touched[n:].zero_()
        cache = None
        if self.device_is_cpu:
            self._ensure(self.bin_cache_, 4 * n)
            cache = self.bin_cache_.view(4 * n)
        _bin.launch_count_tiles(splat_g, radii, camera, touched[:n], dev, **sp, cache=cache)
        wp.utils.array_scan(touched, offsets, inclusive=False)
        n_pairs = int(offsets[n:].numpy()[0])
        t = self._stage("bin_count", t)
        for buf, m in ((self.keys_, 2 * n_pairs), (self.slots_, 2 * n_pairs), (self.pair_gauss_, n_pairs),
                       (self.splats_, n_pairs), (self.splat_rgbz_, n_pairs)):
            self._ensure(buf, max(m, 1))
        keys, slots = self.keys_.full, self.slots_.full
        _bin.launch_emit_pairs(splat_g, depths, radii, offsets[:n], camera, keys, slots, self.pair_gauss_.full,
                               n_pairs, dev, **sp, cache=cache)
        t = self._stage("bin_keys", t)
        n_tiles = camera.tiles_x * camera.tiles_y
        self._ensure(self.ranges_, n_tiles)
        if self.device_is_cpu:
            # one move of the pairs, from the Gaussians' side, and the ranges with it (bin.sort_pairs_and_ranges)
            self._ensure(self.sort_scratch_, _bin.sort_by_gaussian_scratch(n, n_tiles))
            _bin.sort_pairs_and_ranges(keys, slots, n_pairs, n_tiles, offsets[:n], touched[:n],
                                       self.ranges_.view(n_tiles), scratch=self.sort_scratch_.full)
            self._stage("sort", t)
            return n_pairs
        _bin.sort_pairs(keys, slots, n_pairs, n_tiles)
        t = self._stage("sort", t)
        _bin.launch_tile_ranges(keys, n_pairs, self.ranges_.view(n_tiles), dev, **sp)
        self._stage("ranges", t)
        return n_pairs

    # --------------------------------------------------------------------------------------------- forward
    def forward(self, means, log_scales, quats, opacity_logits, sh, camera: Camera,
                background: Sequence[float] = (0.0, 0.0, 0.0), *, sh_degree: int | None = None,
                rgb_only: bool = False) -> RenderOutput:
        """Render RGB, depth and alpha (see :class:`RenderOutput`) and keep what :meth:`backward` needs.

        ``sh_degree``: SH degree to use (default: the full degree of ``sh``; lower uses the first
        ``(sh_degree + 1)^2`` coefficients, as 3DGS does while it raises the degree during training).
        ``background``: RGB (3,), added as ``T_final * background``. ``rgb_only``: the colour image alone, for renders
        that need no gradient (the evaluation, the viewer): where the blend takes a whole tile a thread (the CPU) the
        output's ``depth``, ``alpha``, ``T_final`` and ``n_contrib`` are then None and :meth:`backward` refuses it;
        the blend keeps neither the depth nor the last list position (about 9 % of a 640x480 forward on one Zen 4
        thread; docs/rasteriser.md), the same colours bit for bit. Elsewhere it renders everything.
        """
        self._check_camera(camera)
        params = self._params(means, log_scales, quats, opacity_logits, sh)
        means, log_scales, quats, opacity_logits, sh = params
        if sh is None:
            raise ValueError("forward: sh is required (use render_alpha for coverage only)")
        bg = tuple(float(b) for b in np.asarray(background, np.float64).reshape(-1))
        if len(bg) != 3:
            raise ValueError(f"background: expected 3 values (RGB), got {len(bg)}")
        K = sh.shape[1]
        full_degree = int(round(math.sqrt(K))) - 1
        degree = full_degree if sh_degree is None else int(sh_degree)
        if not 0 <= degree <= full_degree:
            raise ValueError(f"sh_degree={sh_degree}: sh has K={K} coefficients (degree {full_degree})")
        num_bases = (degree + 1) ** 2
        dev, sp = self.device, self._split
        n = means.shape[0]
        self._generation += 1
        if self.profile:
            self.timings = {}
        n_pairs = self._project_and_bin(means, log_scales, quats, opacity_logits, camera)
        t = time.perf_counter()
        radii = self.radii_.view(n)
        rgbz_g = self.rgbz_g_.view(n)
        _sh.launch_evaluate_sh(sh, means, num_bases, camera, radii, self.depths_.view(n), rgbz_g, dev, **sp)
        t = self._stage("sh", t)
        _raster.launch_pack_splats(self.slots_.full, self.pair_gauss_.full, self.splat_g_.view(n), rgbz_g, n_pairs,
                                   self.splats_.full, self.splat_rgbz_.full, dev, **sp)
        t = self._stage("pack", t)
        H, W = camera.height, camera.width
        only_rgb = bool(rgb_only) and self.pixels_per_thread == TILE_SIZE * TILE_SIZE
        rgb = self._image("rgb", H, W)
        if only_rgb:
            depth = alpha = T_final = n_contrib = None
        else:
            depth, alpha = self._image("depth", H, W), self._image("alpha", H, W)
            T_final, n_contrib = self._image("T_final", H, W), self._image("n_contrib", H, W)
        _raster.launch_rasterize_forward(camera, self.ranges_.full, self.splats_.full, self.splat_rgbz_.full, bg,
                                         rgb, depth, alpha, T_final, n_contrib, dev, **sp,
                                         seg=self.pixels_per_thread, only_rgb=only_rgb)
        self._stage("blend", t)
        return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, radii=radii, means2d=self.means2d_.view(n).view(
            wp.float32), depths=self.depths_.view(n), tiles_touched=self.tiles_touched_.view(n), n_pairs=n_pairs,
            camera=camera, background=bg, num_bases=num_bases, T_final=T_final, n_contrib=n_contrib,
            params=params, generation=self._generation)

    def render_alpha(self, means, log_scales, quats, opacity_logits, camera: Camera, *, with_depth: bool = False,
                     t_stop: float = 0.0) -> AlphaOutput:
        """Accumulated alpha (H, W), per-Gaussian visibility and, with ``with_depth``, the accumulated depth
        ``sum w z`` (the full render's unnormalised depth): no colours, no SH, no saved state (the cheap coverage
        path for seeding and visibility tests; ``sh`` is not needed).

        Same projection, binning and blending rules as :meth:`forward`; ``1 - alpha`` is the transmittance.
        ``t_stop``: a pixel also stops once an accumulated Gaussian took its transmittance below this, so alpha is
        exact wherever it stays below ``1 - t_stop`` and the depth sum misses at most a weight of ``t_stop``; 0 (or
        anything up to 3DGS's 1e-4) gives the full render's alpha and depth.
        Invalidates the previous :class:`RenderOutput` of this rasteriser.
        """
        self._check_camera(camera)
        t_stop = float(t_stop)
        if not 0.0 <= t_stop < 1.0:
            raise ValueError(f"render_alpha: t_stop must be in [0, 1), got {t_stop}")
        means, log_scales, quats, opacity_logits, _ = self._params(means, log_scales, quats, opacity_logits, None)
        dev, sp = self.device, self._split
        n = means.shape[0]
        self._generation += 1
        if self.profile:
            self.timings = {}
        n_pairs = self._project_and_bin(means, log_scales, quats, opacity_logits, camera)
        t = time.perf_counter()
        _raster.launch_pack_splats(self.slots_.full, self.pair_gauss_.full, self.splat_g_.view(n), None, n_pairs,
                                   self.splats_.full, self.splat_rgbz_.full, dev, **sp,
                                   depths_g=self.depths_.view(n) if with_depth else None)
        t = self._stage("pack", t)
        alpha = self._image("alpha_only", camera.height, camera.width)
        depth = self._image("depth_only", camera.height, camera.width) if with_depth else None
        _raster.launch_rasterize_alpha(camera, self.ranges_.full, self.splats_.full, alpha, dev, **sp,
                                       seg=self.pixels_per_thread, splat_rgbz=self.splat_rgbz_.full, depth=depth,
                                       t_stop=t_stop)
        self._stage("blend", t)
        return AlphaOutput(alpha=alpha, radii=self.radii_.view(n), n_pairs=n_pairs, depth=depth)

    # -------------------------------------------------------------------------------------------- backward
    def backward(self, out: RenderOutput, v_rgb, v_depth=None, v_alpha=None, *, into=None,
                 absgrad: bool = True) -> Gradients:
        """Gradients of ``sum(v_rgb * rgb) + sum(v_depth * depth) + sum(v_alpha * alpha)`` (see :class:`Gradients`).

        ``v_rgb`` (H, W, 3), ``v_depth`` (H, W) or None, ``v_alpha`` (H, W) or None: float32, NumPy or Warp.
        ``out`` must be the latest :meth:`forward` result of this rasteriser. ``into``: optional object with float32
        Warp arrays ``means`` (N, 3), ``log_scales`` (N, 3), ``quats`` (N, 4), ``opacity_logits`` (N,) and ``sh``
        (N, K, 3) on this device (e.g. ``GaussianMap.float_grads()``): the parameter gradients are written there
        (overwritten) instead of into the rasteriser's buffers, which saves the copy; the returned
        :class:`Gradients` then holds those arrays. ``absgrad=False``: skip the AbsGS sums where that saves time
        (the CPU tile kernels: 5-10% of the blend); ``Gradients.absgrad`` is then zero on every path. Densification statistics
        are the owner's:
        ``Gradients.v_means2d``, ``absgrad`` and ``radii`` feed :func:`mgso_kernels.adam.accumulate_stats`
        (``GaussianMap.accumulate_stats``).
        """
        if out.generation == self._generation and out.T_final is None and out.rgb is not None:
            raise ValueError("backward: this RenderOutput was rendered with rgb_only=True (no T_final or n_contrib "
                             "kept); render with forward(..., rgb_only=False) to take a gradient")
        if out.generation != self._generation or out.T_final is None:
            raise RuntimeError("backward: this RenderOutput is stale: the rasteriser ran forward/render_alpha since "
                               "(its buffers were reused); call backward before the next forward, or use one "
                               "Rasterizer per pending frame")
        cam = out.camera
        H, W = cam.height, cam.width
        dev, sp = self.device, self._split
        v_rgb = as_float_array(v_rgb, "v_rgb", (W, 3), dev, H)
        if v_depth is not None:
            v_depth = as_float_array(v_depth, "v_depth", (W,), dev, H)
        if v_alpha is not None:
            v_alpha = as_float_array(v_alpha, "v_alpha", (W,), dev, H)
        means, log_scales, quats, opacity_logits, sh = out.params
        n = means.shape[0]
        m = out.n_pairs
        if self.profile:
            self.timings = {}
        t = time.perf_counter()
        self._ensure(self.pair_grads_, max(m, 1))
        for buf in (self.v_means2d_, self.v_conics_, self.v_opacities_, self.v_colors_, self.v_depths_,
                    self.absgrad_, self.weights_, self.v_means_, self.v_log_scales_, self.v_quats_,
                    self.v_opacity_logits_, self.v_pose_partial_):
            self._ensure(buf, n)
        self._ensure(self.pose_blocks_, max(1, -(-n // _project.POSE_BLOCK)))
        K = sh.shape[1]
        if self.v_sh_ is None or self.v_sh_.tail != (K, 3):
            self.v_sh_ = _Buffer(wp.float32, (K, 3))
        self._ensure(self.v_sh_, n)
        _raster_bwd.launch_rasterize_backward(cam, self.ranges_.full, self.splats_.full, self.splat_rgbz_.full,
                                              self.slots_.full, out.background, out.T_final, out.n_contrib, v_rgb,
                                              v_depth, v_alpha, self.pair_grads_.full, m, dev, **sp,
                                              seg=self.pixels_per_thread, absgrad=absgrad)
        t = self._stage("backward_blend", t)
        v_means2d, v_conics = self.v_means2d_.view(n), self.v_conics_.view(n)
        v_opac, v_colors, v_depths = self.v_opacities_.view(n), self.v_colors_.view(n), self.v_depths_.view(n)
        want_absgrad, absgrad = absgrad, self.absgrad_.view(n)
        weights = self.weights_.view(n)
        _raster_bwd.launch_gather_gaussian_grads(self.pair_offsets_.view(n), self.tiles_touched_.view(n),
                                                 self.pair_grads_.full, v_means2d, v_conics, v_opac, v_colors,
                                                 v_depths, absgrad, weights, dev, **sp)
        if not want_absgrad and self.pixels_per_thread != TILE_SIZE * TILE_SIZE:
            absgrad.zero_()  # the row kernels sum it anyway: same contract on every path
        t = self._stage("backward_gather", t)
        radii = self.radii_.view(n)
        v_means, v_log_scales = self.v_means_.view(n), self.v_log_scales_.view(n)
        v_quats, v_logits = self.v_quats_.view(n), self.v_opacity_logits_.view(n)
        v_pose_partial, v_sh = self.v_pose_partial_.view(n), self.v_sh_.view(n)
        if into is not None:
            v_means, v_log_scales, v_quats, v_logits, v_sh = self._into_arrays(into, n, sh.shape[1])
        _project.launch_project_backward(means, log_scales, quats, opacity_logits, cam, self.eps2d,
                                         self.antialiased, radii, v_means2d, v_conics, v_depths, v_opac, v_means,
                                         v_log_scales, v_quats, v_logits, v_pose_partial, dev, **sp)
        _sh.launch_evaluate_sh_backward(sh, means, out.num_bases, cam, radii, v_colors, v_sh, v_means,
                                        v_pose_partial, dev, **sp)
        _project.launch_reduce_pose(v_pose_partial, self.pose_blocks_.full, self.v_pose, dev, **sp)
        self._stage("backward_project", t)
        return Gradients(v_means=v_means, v_log_scales=v_log_scales, v_quats=v_quats, v_opacity_logits=v_logits,
                         v_sh=v_sh, v_pose=self.v_pose, v_means2d=v_means2d.view(wp.float32),
                         absgrad=absgrad.view(wp.float32), radii=radii, weights=weights)
