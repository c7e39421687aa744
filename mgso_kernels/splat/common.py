"""Definitions shared by the splatting kernels (Warp module with types, constants and ``@wp.func`` only).

The blending rules' constants (3DGS's): a Gaussian is skipped at a pixel where ``alpha < 1/255``, alpha is clamped
at 0.99, and a pixel stops once its transmittance would fall below 1e-4.

``splat`` 8-vector, one per visible Gaussian (written by the projection, copied per (tile, Gaussian) pair before
blending): ``(mean_x, mean_y, a, b, c, opacity, exp(-a), r2)`` with the conic ``(a, b, c)``
(``power = -0.5 (a dx^2 + c dy^2) - b dx dy``) and ``r2`` the squared Mahalanobis radius of the *cut-off ellipse*
``d^T conic d <= r2`` outside which ``opacity exp(power) < 1/255`` (see :func:`cutoff_r2`).

The blend kernels' lane vectors live here too, so that the row kernels (``raster``), their backward (``raster_bwd``)
and the tile-per-thread kernels (``raster_tile``) share them without importing each other: ``vec16`` / ``vec16i``
hold one value per pixel of a tile row (``TILE_SIZE`` lanes), and ``vec16`` also one (tile, Gaussian) pair's gradient
accumulators and blending weight (see ``raster_bwd.gather_gaussian_grads``).
"""

from __future__ import annotations

import warp as wp

from .camera import TILE_SIZE

wp.set_module_options({"enable_backward": False})

__all__ = ["vec6", "vec8", "vec16", "vec16i", "ALPHA_MIN", "ALPHA_MAX", "T_MIN", "R2_REL_MARGIN",
           "R2_ABS_MARGIN", "cutoff_r2", "LANES16_CPP"]

vec6 = wp.types.vector(length=6, dtype=wp.float32)
vec8 = wp.types.vector(length=8, dtype=wp.float32)
vec16 = wp.types.vector(length=TILE_SIZE, dtype=wp.float32)
vec16i = wp.types.vector(length=TILE_SIZE, dtype=wp.int32)

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)
# cut-off ellipse inflation, so float32 rounding can never exclude a pixel the 1/255 test would accept
R2_REL_MARGIN = wp.constant(1.0e-3)
R2_ABS_MARGIN = wp.constant(1.0e-2)


@wp.func
def cutoff_r2(op: float) -> float:
    """Squared Mahalanobis radius where opacity * exp(power) = 1/255, i.e. 2 log(255 opacity), inflated by
    a relative 1e-3 and 1e-2 (a 0.5% margin in alpha at the border)."""
    r2 = 2.0 * wp.log(255.0 * op)
    return r2 * (1.0 + R2_REL_MARGIN) + R2_ABS_MARGIN


# C++ of the CPU's per-Gaussian snippets (bin.py, project.py): 16-lane clang vectors and the scalar operations of
# Warp's CPU code on them, so that a snippet computes what the Warp function computes, bit for bit: a select without
# a branch, Warp's float min/max (C's fminf/fmaxf: a NaN operand gives the other), int min/max, the IEEE square root,
# and float -> int through ceil or floor (a cast truncates, as Warp's int()).
LANES16_CPP = r"""
typedef float vf __attribute__((ext_vector_type(16)));
typedef int vi __attribute__((ext_vector_type(16)));
auto sel = [](vi m, vf a, vf b) -> vf { return (vf)((m & (vi)a) | (~m & (vi)b)); };
auto seli = [](vi m, vi a, vi b) -> vi { return (m & a) | (~m & b); };
auto fmn = [&](vf a, vf b) -> vf { return sel(a <= b, a, sel(b == b, b, a)); };   // wp::min: C's fminf
auto fmx = [&](vf a, vf b) -> vf { return sel(a >= b, a, sel(b == b, b, a)); };   // wp::max: C's fmaxf
auto imn = [&](vi a, vi b) -> vi { return seli(a < b, a, b); };
auto imx = [&](vi a, vi b) -> vi { return seli(a > b, a, b); };
auto sqrtv = [](vf x) -> vf { return __builtin_elementwise_sqrt(x); };
auto ceili = [](vf x) -> vi { return __builtin_convertvector(__builtin_elementwise_ceil(x), vi); };
auto floori = [](vf x) -> vi { return __builtin_convertvector(__builtin_elementwise_floor(x), vi); };
"""
