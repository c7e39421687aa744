"""A kernel that compiles for the CPU and not for CUDA: the negative control of test_cuda_compile.py (a check that
cannot fail on a CUDA-only error would say nothing)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func_native("""
#if defined(__CUDACC__) || defined(__CUDA_ARCH__)
    mgso_no_such_symbol_on_cuda = 1;
#endif
    return a + 1;
""")
def plus_one(a: int) -> int: ...


@wp.kernel
def add_one(x: wp.array(dtype=int)):
    i = wp.tid()
    x[i] = plus_one(x[i])
