"""Work sharing for the CPU's split launches: each chunk takes its own range first, then what the others have left.

:func:`mgso_kernels.runtime.launch_split` gives each core one contiguous range of a launch's threads. Where the
items cost about the same that is the cheapest split, but the rasteriser's items do not: a tile's blend costs what
its list holds, and a block of a map in spatial order (``GaussianMap.sort_spatially``) is either in view or passed
over. The core with the lighter range then waits for the other at the end of every launch; and where another thread
of the process (the odometry) or another process holds a core for a while, the chunk that core was to run waits for
it while the other core idles. Measured on the deterministic 7-Scenes ``mgso run`` (2 cores): the launching thread
waited 16-21 s in all for the other chunk after finishing its own (docs/rasteriser.md, "Python between the kernels,
and the work of two cores").

Here a kernel's chunks are ``threads`` Warp threads (one a core). Chunk ``c`` owns the static split's range ``c`` and
takes its items from the front, one at a time; once its range is empty it takes items from the back of the other
ranges, in turn. A range is one 64-bit word, its front and back (``take_item``: an atomic fetch-and-add on the CPU,
where Warp's own ``atomic_add`` is a plain read-modify-write), so an item is taken once. A core does the range it
would have done under the static split (its data stay in its caches from launch to launch) and helps the other only
at the end: a first version in which every item came from one shared counter balanced the cores as well but cost
the cores' caches as much CPU as it saved (docs/rasteriser.md). Every item is computed by the same code whoever takes
it, and items write disjoint outputs, so the results are the static split's bit for bit. The kernels:
``kernel(offset, shares, n_items, *inputs)`` with the loop ::

    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):
        r = (chunk + k) % chunks
        i = take_item(shares, r, k)
        while i >= 0:
            ...item i...
            i = take_item(shares, r, k)

(``offset`` is :func:`~mgso_kernels.runtime.launch_split`'s, the chunk's index here). CUDA keeps the kernels with a
thread per item; these are for the CPU only.
"""

from __future__ import annotations

import os
import threading
from typing import Any, Sequence

import numpy as np
import warp as wp

__all__ = ["take_item", "launch_dynamic", "launch_shared", "launch_blocks", "use_dynamic", "dynamic_on"]


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
// the range [lo, hi) as one word, lo in the low 32 bits: the front takes lo (adds 1), the back hi - 1 (adds -2^32);
// the item is valid where the word before held lo < hi (a taker that finds the range empty changes it no further)
long long* w = (long long*)shares.data + r;
const long long old = __atomic_fetch_add(w, back == 0 ? 1LL : -(1LL << 32), __ATOMIC_RELAXED);
const int lo = (int)(old & 0xffffffffLL), hi = (int)(old >> 32);
if (lo >= hi) return -1;
return back == 0 ? lo : hi - 1;
#else
return -1;
#endif
""")
def take_item(shares: wp.array(dtype=wp.int64), r: int, back: int) -> int:
    """An item of range ``r`` of ``shares`` (each a word: the range's first item in the low 32 bits, its end in the
    high ones), from its front (``back`` 0) or its back, atomically; -1 once the range is empty."""
    ...


_local = threading.local()
_on = {"on": os.environ.get("MGSO_DYNAMIC_SPLIT", "1") != "0"}


def use_dynamic(on: bool) -> bool:
    """Whether the kernels that have a work-sharing variant run it on the CPU (the default; ``MGSO_DYNAMIC_SPLIT=0``
    in the environment turns it off at import): off, every launch is split statically. The outputs are the same
    either way, bit for bit; for tests and profiles that compare the two. Returns the previous setting."""
    before = _on["on"]
    _on["on"] = bool(on)
    return before


def dynamic_on() -> bool:
    return _on["on"]


def _shares(device: str, chunks: int) -> tuple[wp.array, np.ndarray]:
    """This thread's words for ``chunks`` ranges on ``device`` (a launch waits for its chunks, so the words of a
    launching thread are never shared by two launches at once) and their NumPy view (zero-copy on the CPU)."""
    table = getattr(_local, "shares", None)
    if table is None:
        table = _local.shares = {}
    got = table.get((device, chunks))
    if got is None:
        arr = wp.zeros(chunks, dtype=wp.int64, device=device)
        got = table[(device, chunks)] = (arr, arr.numpy())
    return got


def launch_dynamic(kernel: Any, n_items: int, inputs: Sequence[Any], device: str, *, threads: int | None = None,
                   min_items: int = 1) -> int:
    """Run ``kernel(offset, shares, n_items, *inputs)`` (see the module's doc) on the CPU as one chunk a core:
    ``threads`` chunks (default :func:`~mgso_kernels.runtime.cpu_threads`), fewer where the items are fewer than
    ``min_items`` a chunk, each owning :func:`~mgso_kernels.runtime.split_ranges`' range. Returns the number of
    chunks."""
    from .runtime import cpu_threads, launch_split, split_ranges

    n_items = int(n_items)
    if n_items <= 0:
        return 0
    if n_items >= 1 << 31:
        raise ValueError(f"launch_dynamic: {n_items} items, at most 2^31 - 1")
    n = threads if threads is not None else cpu_threads()
    parts = max(1, min(int(n), n_items // max(1, int(min_items))))
    ranges = split_ranges(n_items, parts)
    shares, view = _shares(str(device), len(ranges))
    view[:] = [(hi << 32) | lo for lo, hi in ranges]
    launch_split(kernel, len(ranges), [shares, n_items, *inputs], device, min_chunk=1, threads=len(ranges))
    return len(ranges)


def launch_shared(dynamic_kernel: Any, n_items: int, inputs: Sequence[Any], status: wp.array, device: str, *,
                  threads: int | None = None, min_items: int = 1) -> bool:
    """Run ``dynamic_kernel(offset, shares, n_items, *inputs, status)`` (:func:`launch_dynamic`) where it applies:
    on the CPU, with :func:`use_dynamic` on, where more than one chunk of at least ``min_items`` items would run.
    Returns whether it ran and did every item (``status``, [n_items] int32, all 1; a snippet that declines an item
    leaves 0): where not, the caller runs its static kernel over every item."""
    from . import runtime

    n = threads if threads is not None else runtime.cpu_threads()
    if not (dynamic_on() and runtime.device_is_cpu(str(device)) and n > 1 and n_items >= 2 * max(1, min_items)):
        return False
    launch_dynamic(dynamic_kernel, n_items, [*inputs, status], device, threads=n, min_items=min_items)
    return bool(status.numpy()[:n_items].all())


def launch_blocks(kernel: Any, dynamic_kernel: Any, n: int, block: int, inputs: Sequence[Any], native: int,
                  device: str, *, threads: int | None = None, min_chunk: int = 4096) -> Any:
    """:func:`mgso_kernels.runtime.launch_blocks` (``kernel(offset, block, n, *inputs, native, status)``, a block of
    ``block`` items a thread, its C++ snippet first) with the blocks shared where :func:`launch_shared` applies and
    the snippets are on: ``dynamic_kernel(offset, shares, n_blocks, block, n, *inputs, status)``, each chunk taking
    its own range's blocks and then what the others have left; where it leaves a block undone (status 0: the snippet
    declined) the static kernel runs every block again. Returns the ``(blocks,)`` int32 status (1 where the snippet
    did the block)."""
    from . import runtime

    n_blocks = -(-int(n) // int(block))
    if native and n_blocks:
        status = wp.empty(n_blocks, dtype=wp.int32, device=device)
        if launch_shared(dynamic_kernel, n_blocks, [int(block), int(n), *inputs], status, device, threads=threads,
                         min_items=max(1, min_chunk // int(block))):
            return status
    return runtime.launch_blocks(kernel, n, block, inputs, native, device, threads=threads, min_chunk=min_chunk)
