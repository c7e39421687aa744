"""The one place that starts Warp for mgso.

It initialises Warp once, points the kernel cache at a stable directory, turns a device name (``cpu``, ``cuda:0``,
``auto``) into a Warp device, and splits pixel-parallel CPU launches over the cores.

Why the split: a Warp CPU launch runs its threads as one serial loop on one core, but it releases the GIL, so two
Python threads launching disjoint halves of the same kernel run on two cores (docs/tracking_kernels.md, "Split
launches on the CPU": 1.9x on two cores for the coarse tracker's and the epipolar search's kernels, identical
output). Only kernels whose outputs do not overlap between chunks may be split: on the CPU
``wp.atomic_add`` is not atomic across launches that run at the same time. Reductions therefore write per-block
partial buffers, and :func:`launch_split` keeps chunk borders on block borders (``align``).

Convention for splittable kernels: the first kernel parameter is ``offset: int`` and the kernel computes its global
index as ``offset + wp.tid()`` over a 1-D launch. :func:`launch_split` passes the offset; on a GPU it launches once
with offset 0.

Nothing here runs at import time: importing ``mgso_kernels`` neither initialises Warp nor compiles anything.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import warp as wp

__all__ = [
    "placeholder",
    "DeviceCalls",
    "count_device_calls",
    "launch_blocks",
    "use_native",
    "native_flag",
    "default_cache_dir",
    "init",
    "is_initialised",
    "resolve_device",
    "device_is_cpu",
    "cuda_device_count",
    "device_or_cpu",
    "device_of",
    "cpu_threads",
    "available_cores",
    "set_cpu_threads",
    "cpu_threads_setting",
    "cpu_threads_here",
    "set_blas_threads",
    "split_ranges",
    "launch_split",
    "ensure_loaded",
    "load_modules",
    "cpu_flags_full_slp",
]

log = logging.getLogger(__name__)

_lock = threading.RLock()
_initialised = False  # Warp started (kernel cache set)
_configured = False  # init() called (the BLAS default applied)
_threads = 0  # 0 = all available cores
# per launching thread: its workers (the odometry launches from two threads) and its cpu_threads_here setting
_local = threading.local()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def default_cache_dir() -> Path:
    """Warp's kernel cache for mgso: ``$WARP_CACHE_PATH`` if set, else ``<user cache>/mgso/warp-<version>``.

    A stable directory means a second run (and CI's second run) loads compiled kernels instead of compiling them
    again (4-7 s a module on a 2-core machine).
    """
    env = os.environ.get("WARP_CACHE_PATH")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mgso" / f"warp-{wp.config.version}"


def cpu_flags_full_slp() -> str:
    """Warp's CPU compiler flags (``wp.config.cpu_compiler_flags``) without its cap on the SLP vectoriser's
    recursion depth (Warp sets ``-slp-recursion-max-depth=4`` against LLVM's 12, for compile time), for a module's
    ``cpu_compiler_flags`` option. With LLVM's depth more of a kernel's arithmetic on its 8 pattern pixels is
    vectorised: the window's linearisation 0.89x the time a call, the activation's depth residuals 0.81x, the same
    bits (docs/tracking_kernels.md, "Compiler options on the CPU"); the tracker's, the epipolar search's and the
    image kernels gained nothing measurable, so only the modules that measured a gain ask for it."""
    flags = wp.config.cpu_compiler_flags
    if flags is None:  # Warp's own meaning of None: the host's features with LLVM's defaults
        return "-march=native"
    out: list[str] = []
    toks = flags.split()
    i = 0
    while i < len(toks):
        t = toks[i]
        if t.startswith("-mllvm=-slp-recursion-max-depth"):
            i += 1
            continue
        if t == "-mllvm" and i + 1 < len(toks) and toks[i + 1].startswith("-slp-recursion-max-depth"):
            i += 2
            continue
        out.append(t)
        i += 1
    return " ".join(out)


def is_initialised() -> bool:
    return _initialised


def init(device: str = "auto", cache_dir: str | os.PathLike | None = None, threads: int | None = None,
         quiet: bool = True, blas_threads: int | None = None) -> str:
    """Initialise Warp (once per process) and return the resolved name of ``device``, for the caller to pass to
    what it makes (nothing keeps it as a default).

    ``device``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (the first CUDA device when there is one, else the CPU).
    ``cache_dir``: where compiled kernels are kept; default :func:`default_cache_dir`. Only honoured when this
    call starts Warp (Warp reads it when it initialises; :func:`cuda_device_count` may have started it before).
    ``threads``: CPU threads for split launches, 0 for all cores; ``None`` keeps the current setting.
    ``blas_threads``: threads NumPy's BLAS may use (:func:`set_blas_threads`); ``None``: 1 on the first call, then
    unchanged.
    """
    global _configured
    with _lock:
        _start(cache_dir, quiet)
        if not _configured:
            _configured = True
            if blas_threads is None:
                blas_threads = 1
        if threads is not None:
            set_cpu_threads(threads)
        if blas_threads is not None:
            set_blas_threads(blas_threads)
        return resolve_device(device)


def _start(cache_dir: str | os.PathLike | None = None, quiet: bool = True) -> None:
    """Start Warp once, with the kernel cache at ``cache_dir`` (default :func:`default_cache_dir`)."""
    global _initialised
    with _lock:
        if _initialised:
            return
        cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        cache.mkdir(parents=True, exist_ok=True)
        wp.config.kernel_cache_dir = str(cache)
        wp.config.quiet = quiet
        if quiet and hasattr(wp, "LOG_WARNING"):  # warp >= 1.19 reads log_level (quiet alone has no effect)
            wp.config.log_level = wp.LOG_WARNING
        wp.init()
        _initialised = True


def cuda_device_count() -> int:
    """CUDA devices Warp can use on this machine (0 without a driver or GPU). Starts Warp if nobody did, without
    choosing a default device (``mgso.config.check_runtime`` asks before the command line calls :func:`init`)."""
    _start()
    return int(wp.get_cuda_device_count()) if wp.is_cuda_available() else 0


def resolve_device(device: str | None = "auto") -> str:
    """Turn ``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` into a Warp device name, with a clear error if absent."""
    if not _initialised:
        init("cpu")
    name = (device or "auto").strip().lower()
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name == "cuda":
        name = "cuda:0"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError(f"device {device!r} was asked for, but Warp sees no CUDA device on this machine; "
                           "use --device cpu (or auto)")
    try:
        wp.get_device(name)
    except Exception as exc:  # Warp raises ValueError/RuntimeError depending on the name
        raise ValueError(f"unknown device {device!r}: expected cpu, cuda, cuda:N or auto ({exc})") from None
    return name


def device_or_cpu(device: str | None) -> str:
    """The device a kernel object or launch runs on: ``device`` resolved (:func:`resolve_device`), the CPU when it
    is ``None``. There is no module-wide default device: whoever makes the object says where it runs (``mgso run``
    passes ``runtime.device`` down; ``init`` returns the name to pass)."""
    return resolve_device(device if device is not None else "cpu")


def device_of(*arrays: Any, default: str | None = None) -> str:
    """The device of the first Warp array among ``arrays`` (a launch on arrays runs where they are); ``default``
    (or the CPU) when none is a Warp array."""
    for a in arrays:
        dev = getattr(a, "device", None)
        if dev is not None and isinstance(a, wp.array):
            return str(dev)
    return device_or_cpu(default)


def cpu_threads() -> int:
    """Number of threads CPU split launches use: this thread's :func:`cpu_threads_here`, else the process's
    :func:`set_cpu_threads`, else every available core."""
    here = getattr(_local, "threads", 0)
    if here > 0:
        return here
    if _threads > 0:
        return _threads
    return available_cores()


@contextlib.contextmanager
def cpu_threads_here(threads: int):
    """The CPU split launches made from this thread use ``threads`` threads inside the block (0: the process's
    setting): for work that already runs one task a core, such as renders evaluated two at a time (the other threads
    of the process keep theirs)."""
    if threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    before = getattr(_local, "threads", 0)
    _local.threads = int(threads)
    try:
        yield
    finally:
        _local.threads = before


_cores_seen = (-1e9, 1)  # (time.monotonic() of the last look, cores)


def available_cores() -> int:
    """The cores this process may run on (its affinity; all of them where there is none), looked up at most once a
    second: every split launch asks, and ``sched_getaffinity`` is a system call (1 % of the odometry's CPU time on
    7-Scenes when it was asked each time; py-spy, 2026-12-02), while a change of affinity (``taskset -p``) is rare."""
    global _cores_seen
    now = time.monotonic()
    if now - _cores_seen[0] < 1.0:
        return _cores_seen[1]
    try:
        n = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        n = max(1, os.cpu_count() or 1)
    _cores_seen = (now, n)
    return n


def cpu_threads_setting() -> int:
    """The setting of :func:`set_cpu_threads` (0 = all available cores), to put back after a temporary change."""
    return _threads


def set_cpu_threads(threads: int) -> None:
    """Set the threads used by CPU split launches (0 = all available cores)."""
    global _threads
    if threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    _threads = int(threads)


def set_blas_threads(threads: int) -> None:
    """Limit the threads of the BLAS behind NumPy/SciPy (``threadpoolctl``, process-wide); 0 = all cores.

    mgso's matrices on the host are small (the window's 64x64 system, a 2000x64 Schur product), and the cores are
    already busy with :func:`launch_split`'s workers: a multi-threaded BLAS then spins against them. Measured on the
    2-core machine while another process was busy: the Schur product ``[64, 2000] x [2000, 64]`` took 53 ms with
    OpenBLAS's 2 threads and 1.05 ms with one. :func:`init` therefore sets 1 unless told otherwise.
    """
    if threads < 0:
        raise ValueError(f"blas_threads must be >= 0, got {threads}")
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=int(threads) if threads > 0 else cpu_threads(), user_api="blas")


def _get_pool(n: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _lock:
        if _pool is None or _pool_size < n:
            if _pool is not None:
                _pool.shutdown(wait=True)
            _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="mgso-warp")
            _pool_size = n
        return _pool


_CPU_DEVICES: dict[str, bool] = {}


def _is_cpu(device: str) -> bool:
    """``wp.get_device(device).is_cpu``, remembered by name (4 us a launch otherwise)."""
    got = _CPU_DEVICES.get(device)
    if got is None:
        got = _CPU_DEVICES[device] = bool(wp.get_device(device).is_cpu)
    return got


def device_is_cpu(device) -> bool:
    """Whether ``device`` (a name or a Warp device) is the CPU."""
    return _is_cpu(device)


def split_ranges(dim: int, parts: int, align: int = 1) -> list[tuple[int, int]]:
    """Split ``range(dim)`` into at most ``parts`` contiguous ranges whose inner borders are multiples of ``align``."""
    if dim <= 0:
        return []
    parts = max(1, int(parts))
    align = max(1, int(align))
    blocks = -(-dim // align)
    parts = min(parts, blocks)
    out = []
    start_block = 0
    for p in range(parts):
        end_block = (blocks * (p + 1)) // parts
        lo, hi = start_block * align, min(dim, end_block * align)
        if hi > lo:
            out.append((lo, hi))
        start_block = end_block
    return out


@functools.lru_cache(maxsize=1024)
def _split_ranges(dim: int, parts: int, align: int) -> tuple[tuple[int, int], ...]:
    """:func:`split_ranges` remembered (a launch's sizes repeat from iteration to iteration; 5 us each time)."""
    return tuple(split_ranges(dim, parts, align))


def ensure_loaded(kernel: Any, device: str) -> None:
    """Compile/load a kernel's module on ``device`` now (on the calling thread), not inside a worker thread."""
    wp.load_module(kernel.module, device=device)


def load_modules(modules: Sequence[Any], device: str) -> None:
    """Compile (or load from the kernel cache) every kernel of ``modules`` (Python modules of kernels) on ``device``
    now. Warp does it at a module's first launch otherwise: in real time that is the first frames, which a compile
    of several seconds (a new install, a new Warp, an edited kernel) would drop."""
    for m in modules:
        wp.load_module(m, device=device)


_native = {"on": True}


def use_native(on: bool) -> bool:
    """Whether the CPU's native C++ snippets run where they apply (the default): the tile blends, the pack, binning,
    projection and sort (:mod:`mgso_kernels.splat`) and Adam's blocks; off, their kernels' own Warp code runs (the
    same results, bit for bit or to float rounding as each module says; for tests and profiles). Returns the
    previous setting."""
    before = _native["on"]
    _native["on"] = bool(on)
    return before


def native_flag() -> int:
    """The kernels' ``native`` argument: 1 when :func:`use_native` is on."""
    return int(_native["on"])


def launch_blocks(kernel: Any, n: int, block: int, inputs: Sequence[Any], native: int, device: str, *,
                  threads: int | None = None, min_chunk: int = 4096) -> Any:
    """The CPU's C++ blocks: ``kernel(offset, block, n, *inputs, native, status)`` with a thread per block of
    ``block`` of the ``n`` items, which runs its native snippet (``native`` 1) and its own Warp loop where that
    declines, spread over the cores by :func:`launch_split` (chunks of at least ``min_chunk`` items). Returns the
    ``(blocks,)`` int32 status the kernel writes (1 where the snippet did the block)."""
    n_blocks = -(-int(n) // int(block))
    status = wp.empty(max(n_blocks, 1), dtype=wp.int32, device=device)
    if n_blocks:
        launch_split(kernel, n_blocks, [int(block), int(n), *inputs, int(native), status], device, threads=threads,
                     min_chunk=max(1, min_chunk // int(block)))
    return status[:n_blocks]


def launch_split(kernel: Any, dim: int, inputs: Sequence[Any], device: str | None = None, *,
                 align: int = 1, min_chunk: int = 4096, threads: int | None = None,
                 record_tape: bool = False, recorded: dict | None = None) -> int:
    """Launch a 1-D kernel ``kernel(offset, *inputs)`` over ``dim`` threads, split over CPU cores.

    The kernel's first parameter must be ``offset: int``; thread ``i`` of a chunk starting at ``lo`` handles
    global index ``lo + i``. Chunk borders are multiples of ``align`` (so per-block partial sums never straddle two
    chunks). Chunks are at least ``min_chunk`` threads, so tiny launches stay single. On CUDA this is one launch.
    Returns the number of chunks launched.

    ``recorded``: a dict of recorded launches, for a kernel launched again and again (an iterative solver's
    workspace, a training step's rasteriser): the chunks' launches are recorded once (``wp.launch(record_cmd=True)``)
    for a kernel and split, and later calls only set the inputs that are not the very objects of the last call (a new
    array, a scalar, another struct; a struct is held by reference, its fields as they are now) before launching: 17
    us against 69 us for a full launch of the tracker's 13 arguments. The entries keep the last call's inputs alive,
    so identity compares are sound; the dict is cleared when it reaches :data:`RECORDED_MAX` entries. A CPU launch of
    more than one chunk without a ``recorded`` of its own uses the calling thread's (recording a launch of a
    rasteriser kernel's 15-20 arguments a chunk took about a thirteenth of a 160x120 training step on two threads).
    """
    device = device or device_of(*inputs)
    if dim <= 0:
        return 0
    args = kernel.adj.args
    if not args or args[0].label != "offset":
        raise TypeError(f"launch_split: kernel {kernel.key!r} must take `offset: int` as its first parameter")
    n = threads if threads is not None else cpu_threads()
    is_cpu = _is_cpu(device)
    parts = 1 if not is_cpu else max(1, min(n, dim // max(1, min_chunk)))
    ranges = _split_ranges(dim, parts, align)
    if recorded is None and not record_tape and len(ranges) > 1:
        recorded = _thread_recorded()
    if recorded is not None and not record_tape:
        # the kernel object, not only its key: the variants a factory makes (``wp.static`` flags) share one key; the
        # inputs' types and arrays' dtypes and ranks: a generic kernel (``Any``) is an overload for each
        key = (id(kernel), kernel.key, str(device), tuple(ranges),
               tuple([(type(a), a.dtype, a.ndim) if isinstance(a, wp.array) else type(a) for a in inputs]))
        entry = recorded.get(key)
        if entry is None:
            if len(recorded) >= RECORDED_MAX:
                recorded.clear()
            cmds = _record(kernel, ranges, inputs, device)
            recorded[key] = (cmds, kernel, list(inputs))  # the inputs of the last launch, kept alive
        else:
            cmds, _, last = entry
            for i, a in enumerate(inputs):
                if a is last[i]:
                    # the very object of the last launch: an array is the same memory, a struct is held by
                    # reference (its fields as they are now), a scalar is the same value
                    continue
                # None until every chunk took it: an input Warp refuses raises here, and the next call sets its input
                # again (a refused object passed again must fail again, not run with the last call's)
                last[i] = None
                if wp.types.is_struct(a):
                    ct = a.__ctype__()  # what Warp's pack_arg makes of a struct, without its chain of type tests
                    for c in cmds:
                        c.set_param_at_index_from_ctype(i + 1, ct)
                else:
                    for c in cmds:
                        c.set_param_at_index(i + 1, a)
                last[i] = a
        return _run(cmds)
    if len(ranges) <= 1:
        wp.launch(kernel, dim=dim, inputs=[0, *inputs], device=device, record_tape=record_tape)
        return 1
    if not record_tape:
        return _run(_record(kernel, ranges, inputs, device))
    ensure_loaded(kernel, device)
    futures = [_get_pool(len(ranges)).submit(partial(wp.launch, kernel, dim=hi - lo, inputs=[lo, *inputs],
                                                     device=device, record_tape=True))
               for lo, hi in ranges[1:]]
    lo, hi = ranges[0]
    wp.launch(kernel, dim=hi - lo, inputs=[lo, *inputs], device=device, record_tape=True)
    for f in futures:
        f.result()
    return len(ranges)


#: Entries a dict of recorded launches keeps (:func:`launch_split`) before it starts again.
RECORDED_MAX = 64


def _thread_recorded() -> dict:
    """The calling thread's recorded launches (:func:`launch_split`)."""
    d = getattr(_local, "recorded", None)
    if d is None:
        d = _local.recorded = {}
    return d


def _record(kernel: Any, ranges: list[tuple[int, int]], inputs: Sequence[Any], device: str) -> list:
    """One recorded launch a chunk, all packed here: a worker of :func:`_run` then only makes the native call,
    which releases the GIL (0.09 ms a split launch against 0.29 ms when each worker packed its own arguments while
    competing for the GIL)."""
    if len(ranges) > 1:
        ensure_loaded(kernel, device)  # compile on this thread, not inside a worker
    return [wp.launch(kernel, dim=hi - lo, inputs=[lo, *inputs], device=device, record_cmd=True)
            for lo, hi in ranges]


class _Worker:
    """A thread that runs one chunk of a split launch at a time, handed over by two locks: 22 us of CPU a split
    launch of two chunks against 49 us through a ``ThreadPoolExecutor`` (its future and queue are Python objects
    both threads take the interpreter lock for; medians of six rounds on the 2-core machine, 2026-12-02, a kernel
    whose two chunks take 3.7 us on one thread)."""

    def __init__(self) -> None:
        self._go = threading.Lock()
        self._go.acquire()
        self._done = threading.Lock()
        self._done.acquire()
        self._job: Any = None
        self._error: BaseException | None = None
        threading.Thread(target=self._loop, name="mgso-warp", daemon=True).start()

    def _loop(self) -> None:
        while True:
            self._go.acquire()
            try:
                self._job()
            except BaseException as e:  # handed to the caller's thread by wait()
                self._error = e
            self._job = None
            self._done.release()

    def start(self, job) -> None:
        self._job = job
        self._go.release()

    def wait(self) -> None:
        self._done.acquire()
        if self._error is not None:
            e, self._error = self._error, None
            raise e


def _workers(n: int) -> list:
    ws = getattr(_local, "workers", None)
    if ws is None:
        ws = _local.workers = []
    while len(ws) < n:
        ws.append(_Worker())
    return ws


def _run(cmds: list) -> int:
    """Launch recorded chunks: the first on this thread, the others on this thread's workers. Returns how many."""
    ws = _workers(len(cmds) - 1)
    started = []
    clean = False
    try:
        for w, c in zip(ws, cmds[1:]):
            w.start(c.launch)
            started.append(w)
        cmds[0].launch()
        clean = True
    finally:
        error = None
        try:
            if not clean:
                # an exception here (a signal's, raised where the interpreter checks for one: the call that records
                # a started worker) may have come between a worker's start and its record: no one would wait for
                # that worker's chunk, and its "done" would answer the next launch's wait while that launch still
                # ran (then a double release that ends the worker: the next wait hangs). Not used again.
                _local.workers = None
            for w in started:
                try:
                    w.wait()
                except Exception as e:  # the chunk's own error
                    error = error or e
        except BaseException:
            # interrupted while waiting (a signal's exception): a worker may still be running its chunk, so these
            # workers are not used again (each ends its chunk and then waits for ever, a daemon)
            _local.workers = None
            raise
        if error is not None:
            raise error
    return len(cmds)


_placeholders: dict = {}


def placeholder(dtype, ndim: int, device) -> wp.array:
    """A one-element array (kept, one a dtype, rank and device) standing in for an argument a kernel variant or a
    launch does not read."""
    key = (dtype, ndim, str(device))
    if key not in _placeholders:
        _placeholders[key] = wp.zeros((1,) * ndim, dtype=dtype, device=device)
    return _placeholders[key]


# ------------------------------------------------------------------------------------------- counting device calls
@dataclass
class DeviceCalls:
    """What :func:`count_device_calls` counted: ``launches``, kernel launches as the device runs them (a split CPU
    launch counts one a chunk, so two on two cores; the same code on CUDA makes one); ``memsets``, arrays zeroed or
    filled (``zero_``, ``fill_``: a memset launch on CUDA); ``scans`` (``wp.utils.array_scan``); ``host_reads``,
    ``array.numpy()`` calls (on CUDA each copies to the host and waits for the device, on the CPU a view); ``syncs``,
    explicit ``wp.synchronize`` / ``wp.synchronize_device`` calls."""

    launches: int = 0
    memsets: int = 0
    scans: int = 0
    host_reads: int = 0
    syncs: int = 0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@contextlib.contextmanager
def count_device_calls():
    """Count the Warp calls that reach the device while the block runs (:class:`DeviceCalls`, yielded and filled in
    as they happen), from every thread: a profiling aid (issue 42 asks for the launches and host synchronisations of a
    training step), which wraps Warp's entry points in this process for the block's duration, so run nothing else
    meanwhile. Launches recorded for later (``record_cmd=True``) count when they run."""
    import warp._src.context as ctx
    import warp._src.types as wtypes

    calls = DeviceCalls()
    lock = threading.Lock()
    inside = threading.local()      # a counted call made inside another (a strided zero_ fills) counts once

    def counted(field, fn, skip=None):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if getattr(inside, "depth", 0) == 0 and (skip is None or not skip(args, kwargs)):
                with lock:
                    setattr(calls, field, getattr(calls, field) + 1)
            inside.depth = getattr(inside, "depth", 0) + 1
            try:
                return fn(*args, **kwargs)
            finally:
                inside.depth -= 1
        return wrapper

    patches = [(wp, "launch", counted("launches", wp.launch, lambda a, k: bool(k.get("record_cmd")))),
               (ctx.Launch, "launch", counted("launches", ctx.Launch.launch)),
               (wtypes.array, "zero_", counted("memsets", wtypes.array.zero_)),
               (wtypes.array, "fill_", counted("memsets", wtypes.array.fill_)),
               (wp.utils, "array_scan", counted("scans", wp.utils.array_scan)),
               (wtypes.array, "numpy", counted("host_reads", wtypes.array.numpy)),
               (wp, "synchronize", counted("syncs", wp.synchronize)),
               (wp, "synchronize_device", counted("syncs", wp.synchronize_device))]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    try:
        for obj, name, fn in patches:
            setattr(obj, name, fn)
        yield calls
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)
