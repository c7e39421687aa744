"""Every kernel module compiles for CUDA, on a machine without a GPU.

The kernels are written once for both devices, but the development machines have no GPU, and code that the CPU's
compiler takes can still fail NVIDIA's (a type conversion, a name, an intrinsic). Warp ships NVRTC, so a module can
be compiled to PTX ahead of time (``wp.compile_aot_module(module, arch=...)``) with no GPU or driver: each module of
``mgso_kernels`` with kernels is compiled here for one architecture (the oldest this Warp's NVRTC supports from
sm_75 on; PTX runs on newer GPUs through the driver's JIT). It does not run them: results on a GPU are still to be
measured (docs/gpu.md). The PTX goes to ``<Warp kernel cache>/cuda-check`` and is reused while a module is
unchanged (about 36 s for all modules the first time on the 2-core machine, milliseconds after).
"""

from __future__ import annotations

import ctypes
import importlib
import pkgutil
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import mgso_kernels
import mgso_kernels.splat


def _kernel_modules() -> list[str]:
    names = []
    for pkg in (mgso_kernels, mgso_kernels.splat):
        for info in pkgutil.iter_modules(pkg.__path__, pkg.__name__ + "."):
            if info.ispkg or info.name == "mgso_kernels.runtime":
                continue
            mod = importlib.import_module(info.name)
            if any(isinstance(v, wp.Kernel) and v.module.name == mod.__name__ for v in vars(mod).values()) or any(
                    isinstance(v, dict) and any(isinstance(k, wp.Kernel) for k in v.values())
                    for v in vars(mod).values()):
                names.append(info.name)
    return names


KERNEL_MODULES = _kernel_modules()


def _ptx_arch() -> int:
    """The architecture to compile for; skips when this Warp build has no NVRTC (a CPU-only build)."""
    try:
        from warp._src import context

        core = context.runtime.core
        n = int(core.wp_nvrtc_supported_arch_count())
        archs = (n * ctypes.c_int)()
        core.wp_nvrtc_supported_archs(archs)
        supported = sorted(int(a) for a in archs)
    except Exception as e:  # noqa: BLE001 - any failure here means: no CUDA compiler in this Warp build
        pytest.skip(f"this Warp build cannot compile CUDA code here ({type(e).__name__}: {e})")
    usable = [a for a in supported if a >= 75]
    if not usable:
        pytest.skip(f"this Warp build's NVRTC supports no architecture from sm_75 on (it lists {supported})")
    return usable[0]


@pytest.fixture(scope="module")
def ptx_dir(wp_device) -> Path:
    d = Path(wp.config.kernel_cache_dir) / "cuda-check"
    d.mkdir(parents=True, exist_ok=True)
    return d


def test_the_kernel_modules_are_found():
    # the discovery must not come back short (a test over no modules checks nothing)
    for name in ("mgso_kernels.track", "mgso_kernels.window", "mgso_kernels.initializer", "mgso_kernels.trace",
                 "mgso_kernels.splat.raster_tile", "mgso_kernels.loss_chunks"):
        assert name in KERNEL_MODULES
    assert len(KERNEL_MODULES) >= 15


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_compiles_for_cuda(name, ptx_dir):
    arch = _ptx_arch()
    mod = importlib.import_module(name)
    paths = wp.compile_aot_module(mod, arch=arch, module_dir=ptx_dir, use_ptx=True)
    assert paths and all(Path(p).is_file() and Path(p).stat().st_size > 0 for p in paths), paths
    assert b".entry" in Path(paths[0]).read_bytes()  # PTX with kernel entry points


def test_a_cuda_only_error_fails_the_check(wp_device, ptx_dir, monkeypatch):
    """The negative control: a kernel that runs on the CPU but whose code does not compile for CUDA."""
    arch = _ptx_arch()
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    ctrl = importlib.import_module("_cuda_only_error")
    x = wp.array(np.arange(4, dtype=np.int32), device="cpu")
    wp.launch(ctrl.add_one, dim=4, inputs=[x], device="cpu")
    assert x.numpy().tolist() == [1, 2, 3, 4]
    with pytest.raises(Exception, match="(?i)cuda kernel build failed|compil"):  # NVRTC names the symbol on stderr
        wp.compile_aot_module(ctrl, arch=arch, module_dir=ptx_dir / "control", use_ptx=True)
