"""The pyramid kernels' rows on the CPU as plain loops over pointers (native snippets in Warp's kernels).

:func:`gradients_span` and :func:`downsample_span` do what one thread of
:func:`mgso_kernels.image.compute_gradients` and :func:`mgso_kernels.image.downsample_image` does (a span of one
row), with the same float32 operations in the same order, one per statement (so no contraction into FMAs): the
same bits. Written as loops over row pointers, with the image borders peeled off the gradient's loop, clang
vectorises them; Warp's generated code indexes every pixel through the array's strides and does not (a 640x480
pyramid in 0.74-0.81 against 2.37 ms of one thread: docs/tracking_kernels.md, "The pyramid's rows as plain loops").

Each returns 1, or 0 where it does not apply (on CUDA, the snippets' ``#else``; or for arrays whose rows are not
contiguous), and the kernel then runs its Warp loop.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

# C++ shared by the 8-lane snippets (mgso_kernels.track_simd, mgso_kernels.initializer_simd): the bilinear
# (I, dx, dy) at the 8 lanes' pixels ``ku, kv`` (v8f) into ``s0, s1, s2`` (v8f, declared here), read lane by lane
# (DSO getInterpolatedElement33). Needs in scope: the typedef v8f, ``dIp`` (the level's bytes), ``sdy, sdx`` (its
# strides) and ``w2, h2`` (its width and height minus 2, as float).
SAMPLE8_CPP = r"""
    v8f s0, s1, s2;
    for (int l = 0; l < 8; ++l) {
        const float x = ku[l], y = kv[l];
        // the cell clamped in float first: (int) of NaN or of a huge value is undefined
        const int ix = (int)__builtin_fminf(__builtin_fmaxf(x, 0.0f), w2);
        const int iy = (int)__builtin_fminf(__builtin_fmaxf(y, 0.0f), h2);
        const float ax = x - (float)ix, ay = y - (float)iy, axy = ax * ay;
        const float c11 = axy, c10 = ay - axy, c01 = ax - axy, c00 = 1.0f - ax - ay + axy;
        const float* d00 = (const float*)(dIp + (long)iy * sdy + (long)ix * sdx);
        const float* d01 = (const float*)(dIp + (long)iy * sdy + (long)(ix + 1) * sdx);
        const float* d10 = (const float*)(dIp + (long)(iy + 1) * sdy + (long)ix * sdx);
        const float* d11 = (const float*)(dIp + (long)(iy + 1) * sdy + (long)(ix + 1) * sdx);
        s0[l] = c11 * d11[0] + c10 * d10[0] + c01 * d01[0] + c00 * d00[0];
        s1[l] = c11 * d11[1] + c10 * d10[1] + c01 * d01[1] + c00 * d00[1];
        s2[l] = c11 * d11[2] + c10 * d10[2] + c01 * d01[2] + c00 * d00[2];
    }
"""

_GRADIENTS = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
const int h = img.shape[0], w = img.shape[1];
if (img.strides[1] != 4 || dI.strides[1] != 12 || grad_sq.strides[1] != 4) return 0;
const char* base = (const char*)img.data;
const float* __restrict__ row = (const float*)(base + (long)y * img.strides[0]);
const float* __restrict__ rowm = (const float*)(base + (long)(y > 0 ? y - 1 : 0) * img.strides[0]);
const float* __restrict__ rowp = (const float*)(base + (long)(y < h - 1 ? y + 1 : h - 1) * img.strides[0]);
float* __restrict__ d = (float*)((char*)dI.data + (long)y * dI.strides[0]);
float* __restrict__ g = (float*)((char*)grad_sq.data + (long)y * grad_sq.strides[0]);
// one pixel, as the Warp loop: central differences (clamped at the border), non-finite -> 0
auto one = [&](int x, int xm, int xp) {
    const float ddx = row[xp] - row[xm];
    const float ddy = rowp[x] - rowm[x];
    float dx = 0.5f * ddx;
    float dy = 0.5f * ddy;
    dx = (dx - dx == 0.0f) ? dx : 0.0f;
    dy = (dy - dy == 0.0f) ? dy : 0.0f;
    d[3 * x] = row[x];
    d[3 * x + 1] = dx;
    d[3 * x + 2] = dy;
    const float a = dx * dx;
    const float b = dy * dy;
    g[x] = a + b;
};
// the first and last column apart: the loop between them has no clamp and vectorises
const int lo = x0 > 1 ? x0 : 1, hi = x1 < w - 1 ? x1 : w - 1;
for (int x = x0; x < x1 && x < lo; ++x) one(x, x > 0 ? x - 1 : 0, x < w - 1 ? x + 1 : w - 1);
for (int x = lo; x < hi; ++x) one(x, x - 1, x + 1);
for (int x = hi > lo ? hi : lo; x < x1; ++x) one(x, x > 0 ? x - 1 : 0, x < w - 1 ? x + 1 : w - 1);
return 1;
#else
return 0;
#endif
"""

_DOWNSAMPLE = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (src.strides[1] != 4 || dst.strides[1] != 4) return 0;
const char* base = (const char*)src.data;
const float* __restrict__ r0 = (const float*)(base + (long)(2 * y) * src.strides[0]);
const float* __restrict__ r1 = (const float*)(base + (long)(2 * y + 1) * src.strides[0]);
float* __restrict__ o = (float*)((char*)dst.data + (long)y * dst.strides[0]);
for (int x = x0; x < x1; ++x) {
    const float a = r0[2 * x] + r0[2 * x + 1];
    const float b = a + r1[2 * x];
    const float c = b + r1[2 * x + 1];
    o[x] = 0.25f * c;
}
return 1;
#else
return 0;
#endif
"""


@wp.func_native(_GRADIENTS)
def gradients_span(img: wp.array2d(dtype=float), dI: wp.array2d(dtype=wp.vec3), grad_sq: wp.array2d(dtype=float),
                   y: int, x0: int, x1: int) -> int:
    """Pixels ``[x0, x1)`` of row ``y`` of :func:`mgso_kernels.image.compute_gradients`; 1, or 0 (nothing written)."""
    ...


@wp.func_native(_DOWNSAMPLE)
def downsample_span(src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float), y: int, x0: int, x1: int) -> int:
    """Pixels ``[x0, x1)`` of row ``y`` of :func:`mgso_kernels.image.downsample_image`; 1, or 0 (nothing written)."""
    ...
