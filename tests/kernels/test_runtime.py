import signal
import threading
import time

import numpy as np
import pytest
import warp as wp

from mgso_kernels import runtime


@wp.kernel(enable_backward=False)
def box_blur3(offset: int, img: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    i = offset + wp.tid()
    h = img.shape[0]
    w = img.shape[1]
    y = i // w
    x = i - y * w
    acc = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            yy = wp.clamp(y + dy, 0, h - 1)
            xx = wp.clamp(x + dx, 0, w - 1)
            acc += img[yy, xx]
    out[y, x] = acc / 9.0


def test_split_ranges_cover_and_align():
    for dim in [1, 7, 100, 4097, 100000]:
        for parts in [1, 2, 3, 8]:
            for align in [1, 16, 64]:
                r = runtime.split_ranges(dim, parts, align)
                assert r[0][0] == 0 and r[-1][1] == dim
                assert all(a[1] == b[0] for a, b in zip(r, r[1:]))
                assert all(lo % align == 0 for lo, _ in r)
                assert len(r) <= parts


def test_split_launch_equals_single_launch(wp_device):
    rng = np.random.default_rng(0)
    img = rng.random((240, 320)).astype(np.float32)
    a = wp.array(img, dtype=wp.float32, device=wp_device)
    single = wp.zeros_like(a)
    split = wp.zeros_like(a)
    n1 = runtime.launch_split(box_blur3, img.size, [a, single], wp_device, threads=1)
    n2 = runtime.launch_split(box_blur3, img.size, [a, split], wp_device, threads=4, min_chunk=1000)
    assert n1 == 1
    if wp.get_device(wp_device).is_cpu:
        assert n2 == 4
    assert np.array_equal(single.numpy(), split.numpy())
    # and both equal the obvious NumPy twin
    pad = np.pad(img, 1, mode="edge")
    ref = sum(pad[1 + dy:1 + dy + 240, 1 + dx:1 + dx + 320] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9.0
    assert np.allclose(single.numpy(), ref, atol=1e-6)


def test_threads_here_set_this_threads_split_launches_only():
    """runtime.cpu_threads_here(1) (the evaluation's renders, a frame a core): a split launch inside the block is
    one chunk while another thread's is still split by the process's setting; the setting comes back after the
    block, an error in it included."""
    img = np.random.default_rng(1).random((64, 128)).astype(np.float32)
    a = wp.array(img, dtype=wp.float32, device="cpu")
    out = wp.zeros_like(a)
    before = runtime.cpu_threads_setting()
    runtime.set_cpu_threads(3)
    try:
        assert runtime.launch_split(box_blur3, img.size, [a, out], "cpu", min_chunk=1000) == 3
        seen = {}
        with runtime.cpu_threads_here(1):
            assert runtime.cpu_threads() == 1
            seen["here"] = runtime.launch_split(box_blur3, img.size, [a, out], "cpu", min_chunk=1000)
            other = threading.Thread(target=lambda: seen.__setitem__("other", runtime.launch_split(
                box_blur3, img.size, [a, out], "cpu", min_chunk=1000)))
            other.start()
            other.join(10)
        assert seen == {"here": 1, "other": 3}
        assert runtime.cpu_threads() == 3                              # back after the block
        with pytest.raises(RuntimeError, match="inside"), runtime.cpu_threads_here(2):
            raise RuntimeError("inside")
        assert runtime.cpu_threads() == 3
        with runtime.cpu_threads_here(0):                              # 0: the process's setting
            assert runtime.cpu_threads() == 3
        with pytest.raises(ValueError, match=">= 0"), runtime.cpu_threads_here(-1):
            pass
    finally:
        runtime.set_cpu_threads(before)


def test_split_requires_offset_parameter(wp_device):
    @wp.kernel(enable_backward=False)
    def no_offset(a: wp.array(dtype=float)):
        a[wp.tid()] = 1.0

    with pytest.raises(TypeError, match="offset"):
        runtime.launch_split(no_offset, 10, [wp.zeros(10, dtype=float, device=wp_device)], wp_device)


def test_resolve_device(wp_device):
    assert runtime.resolve_device("cpu") == "cpu"
    assert runtime.resolve_device("auto") in ("cpu", "cuda:0")
    if not wp.is_cuda_available():
        with pytest.raises(RuntimeError, match="no CUDA"):
            runtime.resolve_device("cuda:0")
    with pytest.raises(ValueError, match="unknown device"):
        runtime.resolve_device("tpu")


@wp.kernel(enable_backward=False)
def scale_add(offset: int, gain: float, src: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    i = offset + wp.tid()
    out[i] = gain * src[i] + float(i)


def test_recorded_launches_follow_new_scalars_and_arrays(wp_device):
    """launch_split(recorded=...) replays recorded launches: a changed scalar input and a new array must reach the
    kernel (set into the recorded launch, one recording a split), and the result must equal a plain launch, split over
    the cores or not."""
    rng = np.random.default_rng(1)
    src = wp.array(rng.random(20000).astype(np.float32), device=wp_device)
    src2 = wp.array(rng.random(20000).astype(np.float32), device=wp_device)
    out = wp.zeros(20000, dtype=wp.float32, device=wp_device)
    ref = wp.zeros_like(out)
    cache: dict = {}
    for gain, s in [(2.0, src), (3.0, src), (3.0, src2), (-1.0, src)]:
        for threads in (1, 2):
            n = runtime.launch_split(scale_add, 20000, [gain, s, out], wp_device, min_chunk=1000, threads=threads,
                                     recorded=cache)
            runtime.launch_split(scale_add, 20000, [gain, s, ref], wp_device, min_chunk=1000, threads=threads)
            np.testing.assert_array_equal(out.numpy(), ref.numpy())
            np.testing.assert_allclose(out.numpy(), gain * s.numpy() + np.arange(20000), rtol=1e-6)
            assert n == (threads if wp.get_device(wp_device).is_cpu else 1)
    assert len(cache) == (2 if wp.get_device(wp_device).is_cpu else 1)  # a recording for 1 and for 2 chunks


@wp.struct
class _Gain:
    g: float


@wp.kernel(enable_backward=False)
def scale_add_struct(offset: int, gain: _Gain, src: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    i = offset + wp.tid()
    out[i] = gain.g * src[i] + float(i)


def test_split_cpu_launches_of_a_generic_kernel_keep_each_overloads_recording():
    """A generic kernel (``dtype=Any``) is an overload for each dtype: replaying the recording of one with the arrays
    of another must not happen (the Gaussian map's gather of vec3 rows, then of vec4 rows, failed so). Each dtype's
    launch gives the gathered rows, alternating, on several chunks."""
    from mgso_kernels import adam as kadam

    rng = np.random.default_rng(3)
    n = 9000
    index = wp.array(rng.permutation(n).astype(np.int32), device="cpu")
    for _ in range(2):
        for dt, width in ((wp.vec3, 3), (wp.vec4, 4), (wp.float32, 1)):
            src_np = rng.random((n, width)).astype(np.float32).reshape((n,) if width == 1 else (n, width))
            src = wp.array(src_np, dtype=dt, device="cpu")
            dst = wp.zeros(n, dtype=dt, device="cpu")
            assert runtime.launch_split(kadam.gather_rows, n, [src, index, dst], "cpu", min_chunk=1000,
                                        threads=2) == 2
            np.testing.assert_array_equal(dst.numpy(), src_np[index.numpy()])


def test_split_cpu_launches_replay_the_threads_recordings():
    """A CPU launch of several chunks without a ``recorded`` of its own replays the calling thread's recording of the
    same kernel and split: new arrays, new scalars, a new struct and a struct changed in place all reach the kernel
    (the result equals the formula every time), one recording for all the calls; a launch of one chunk records
    nothing; the thread's dict starts again at RECORDED_MAX entries."""
    rng = np.random.default_rng(2)
    srcs = [wp.array(rng.random(20000).astype(np.float32), device="cpu") for _ in range(3)]
    outs = [wp.zeros(20000, dtype=wp.float32, device="cpu") for _ in range(2)]
    rec = runtime._thread_recorded()
    rec.clear()
    gain = _Gain()
    for k, g in enumerate([2.0, 3.0, 3.0, -1.0, 0.5]):
        s, o = srcs[k % 3], outs[k % 2]
        if k == 2:
            gain = _Gain()                  # a new struct object
        gain.g = g                          # changed in place (k = 1, 3, 4)
        assert runtime.launch_split(scale_add_struct, 20000, [gain, s, o], "cpu", min_chunk=1000, threads=2) == 2
        np.testing.assert_allclose(o.numpy(), g * s.numpy() + np.arange(20000), rtol=1e-6)
        assert runtime.launch_split(scale_add, 20000, [g, s, o], "cpu", min_chunk=1000, threads=2) == 2
        np.testing.assert_allclose(o.numpy(), g * s.numpy() + np.arange(20000), rtol=1e-6)
    assert len(rec) == 2                    # one recording a kernel and split
    bad = wp.zeros(20000, dtype=wp.int32, device="cpu")
    for _ in range(2):                      # refused each time (its dtype: a recording of its own, which fails)
        with pytest.raises(RuntimeError, match="src"):
            runtime.launch_split(scale_add, 20000, [1.0, bad, outs[0]], "cpu", min_chunk=1000, threads=2)
    runtime.launch_split(scale_add, 20000, [4.0, srcs[1], outs[0]], "cpu", min_chunk=1000, threads=2)
    np.testing.assert_allclose(outs[0].numpy(), 4.0 * srcs[1].numpy() + np.arange(20000), rtol=1e-6)
    runtime.launch_split(scale_add, 20000, [1.0, srcs[0], outs[0]], "cpu", min_chunk=1000, threads=1)
    assert len(rec) == 2                    # one chunk: a plain launch
    for n in range(runtime.RECORDED_MAX):   # other splits of the same kernel fill the dict, then it starts again
        runtime.launch_split(scale_add, 2000 + 2 * n, [1.0, srcs[0], outs[0]], "cpu", min_chunk=1, threads=2)
    assert 0 < len(rec) < runtime.RECORDED_MAX


def test_the_device_is_passed_not_a_module_default(wp_device, monkeypatch):
    """Issue 14: the device an object runs on is what its maker passed. ``init`` keeps no default (an object made
    without ``device=`` runs on the CPU), launches on arrays run where the arrays are, and the DSO odometry hands its
    own device to every part it makes (the pixel selector used to follow the last ``init()``: the mapper's device when
    ``runtime.odometry_device`` differed)."""
    import numpy as np
    import warp as wp

    from mgso.config import Config
    from mgso.odometry import Odometry, geometry_for

    assert not hasattr(runtime, "default_device")
    # the rule itself (under MGSO_TEST_DEVICE=cuda the conftest maps an unnamed device to the test device; the
    # function mgso calls is the one it wraps)
    rule = getattr(runtime.device_or_cpu, "unpatched", runtime.device_or_cpu)
    assert rule(None) == "cpu" and rule("cpu") == "cpu"
    a = wp.zeros(4, dtype=wp.float32, device=wp_device)
    assert runtime.device_of(np.zeros(3), a) == str(a.device) and runtime.device_of(np.zeros(3)) == "cpu"
    calls = []
    real = runtime.device_or_cpu
    monkeypatch.setattr(runtime, "device_or_cpu", lambda d: calls.append(d) or real(d))
    odo = Odometry(geometry_for(160, 120, 150.0, 150.0, 79.5, 59.5, Config()), Config(), device=wp_device)
    parts = [odo.window, odo.tracker, odo.initializer, odo.selector, odo.back_end]
    assert all(getattr(p, "device", wp_device) == wp_device for p in parts)
    assert odo.selector.device == wp_device and None not in calls      # nothing fell back to the CPU rule


class _Chunk:
    """A stand-in for a recorded launch: records the thread it ran on, may fail."""

    def __init__(self, fail=False, wait=None):
        self.fail, self.wait, self.thread = fail, wait, None

    def launch(self):
        if self.wait is not None:
            self.wait.wait(5)
        self.thread = threading.get_ident()
        if self.fail:
            raise RuntimeError("chunk failed")


def test_split_chunks_run_on_workers_and_their_errors_reach_the_caller():
    chunks = [_Chunk() for _ in range(3)]
    assert runtime._run(chunks) == 3
    me = threading.get_ident()
    assert chunks[0].thread == me and {c.thread for c in chunks[1:]}.isdisjoint({me})
    assert chunks[1].thread != chunks[2].thread
    with pytest.raises(RuntimeError, match="chunk failed"):
        runtime._run([_Chunk(), _Chunk(fail=True)])
    again = [_Chunk(), _Chunk()]  # the workers are still usable after a chunk's error
    assert runtime._run(again) == 2 and again[1].thread not in (None, me)
    # two threads launching at once each use their own workers (the odometry's tracking and mapping threads)
    gate = threading.Event()
    slow = [_Chunk(), _Chunk(wait=gate)]
    other = threading.Thread(target=runtime._run, args=(slow,))
    other.start()
    fast = [_Chunk(), _Chunk()]
    runtime._run(fast)  # does not wait for the other thread's held chunk
    assert fast[1].thread is not None and slow[1].thread is None
    gate.set()
    other.join(5)
    assert slow[1].thread is not None and slow[1].thread != fast[1].thread


def test_a_split_launch_interrupted_while_waiting_drops_its_workers():
    """A signal's exception while the caller waits for a worker: that worker may still be running its chunk, so
    it is not handed the next launch (which would then be waited for by a stale release)."""
    gate = threading.Event()
    held = _Chunk(wait=gate)
    runtime._run([_Chunk(), _Chunk()])
    before = runtime._local.workers[0]

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.2)
        with pytest.raises(KeyboardInterrupt):
            runtime._run([_Chunk(), held])
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert held.thread is None  # still held when the caller gave up
    after = [_Chunk(), _Chunk()]
    assert runtime._run(after) == 2 and after[1].thread is not None
    assert runtime._local.workers[0] is not before  # new workers
    gate.set()


class _Slow(_Chunk):
    def launch(self):
        time.sleep(0.2)
        super().launch()


def test_a_split_launch_interrupted_between_a_workers_start_and_its_record_drops_its_workers(monkeypatch):
    """A signal's exception right after a worker was handed its chunk, before ``_run`` counted it (found looking
    for the cause of the CI failure of 2026-12-07, a SIGTERM'd run that never ended). Nobody waited for that chunk, so its worker's "done" answered
    the next launch's wait at once while the next chunk still ran. The control: the same launch, uninterrupted,
    keeps its workers."""
    def body(out):
        runtime._run([_Chunk(), _Chunk()])
        out["before"] = runtime._local.workers[0]
        real = runtime._Worker.start

        def start_then_signal(self, job):
            real(self, job)
            monkeypatch.setattr(runtime._Worker, "start", real)
            raise KeyboardInterrupt     # where the interpreter ran the signal's handler

        monkeypatch.setattr(runtime._Worker, "start", start_then_signal)
        try:
            runtime._run([_Chunk(), _Chunk()])
        except KeyboardInterrupt:
            out["interrupted"] = True
        after = [_Chunk(), _Slow()]
        runtime._run(after)
        out["waited"] = after[1].thread is not None      # the launch returned once its chunks had run
        out["new"] = runtime._local.workers[0] is not out["before"]
        kept = runtime._local.workers[0]
        control = [_Chunk(), _Slow()]
        runtime._run(control)
        out["control"] = runtime._local.workers[0] is kept and control[1].thread is not None

    out = {}
    t = threading.Thread(target=body, args=(out,))      # its own workers (thread-local), not the test runner's
    t.start()
    t.join(10)
    assert out.get("interrupted") and out.get("waited") and out.get("new") and out.get("control")


def test_full_slp_flags_drop_only_warps_slp_depth_cap(monkeypatch):
    monkeypatch.setattr(wp.config, "cpu_compiler_flags",
                        "-march=native -mllvm=-inline-threshold=9000 -mllvm=-slp-recursion-max-depth=4")
    assert runtime.cpu_flags_full_slp() == "-march=native -mllvm=-inline-threshold=9000"
    monkeypatch.setattr(wp.config, "cpu_compiler_flags", "-march=native -mllvm -slp-recursion-max-depth=4 -O1")
    assert runtime.cpu_flags_full_slp() == "-march=native -O1"
    monkeypatch.setattr(wp.config, "cpu_compiler_flags", None)  # Warp's None: host features, LLVM's defaults
    assert runtime.cpu_flags_full_slp() == "-march=native"
    monkeypatch.setattr(wp.config, "cpu_compiler_flags", "")  # a generic target stays generic
    assert runtime.cpu_flags_full_slp() == ""


def test_the_modules_that_measured_a_gain_carry_their_compiler_options():
    """docs/tracking_kernels.md "Compiler options on the CPU": the window's and the activation's kernels with LLVM's
    full SLP depth, the initialiser's at -O3; the tracker's module (no gain measured) keeps Warp's defaults."""
    from mgso_kernels import activation, initializer, track, window

    def opts(m):
        return wp.get_module(m.__name__).options

    for m in (window, activation):
        flags = opts(m)["cpu_compiler_flags"]
        assert flags is not None and "slp-recursion-max-depth" not in flags and "-march=native" in flags
    assert opts(initializer)["optimization_level"] == 3
    track_flags = opts(track)["cpu_compiler_flags"]  # None: Warp's global flags, which cap the SLP depth
    assert track_flags is None or "slp-recursion-max-depth" in track_flags
    assert opts(track)["optimization_level"] in (None, 2)


def test_count_device_calls_counts_what_reaches_the_device(wp_device):
    """runtime.count_device_calls (issue 42: a training step's launches and host synchronisations): a plain launch
    is one, a recorded one counts when it runs (not when recorded), a split CPU launch one a chunk; zero_ and fill_
    are memsets (a strided zero_, which fills, once); scans, numpy() reads and explicit synchronisations each count;
    nothing is counted outside the block, and Warp's functions are themselves again after it."""
    src = wp.array(np.arange(8192, dtype=np.float32), device=wp_device)
    out = wp.zeros(8192, dtype=wp.float32, device=wp_device)
    launch, numpy_read = wp.launch, wp.array.numpy
    with runtime.count_device_calls() as calls:
        wp.launch(scale_add, dim=8192, inputs=[0, 2.0, src, out], device=wp_device)
        cmd = wp.launch(scale_add, dim=8192, inputs=[0, 2.0, src, out], device=wp_device, record_cmd=True)
        assert calls.launches == 1
        cmd.launch()
        chunks = runtime.launch_split(scale_add, 8192, [2.0, src, out], wp_device, min_chunk=1024, threads=2)
        out.zero_()
        wp.zeros((4, 4), dtype=wp.float32, device=wp_device)[:, :2].zero_()   # strided: zero_ fills
        out.fill_(1.0)
        wp.utils.array_scan(wp.zeros(4, dtype=wp.int32, device=wp_device),
                            wp.zeros(4, dtype=wp.int32, device=wp_device))
        out.numpy()
        wp.synchronize_device(wp_device)
    # three memsets of ours and the three of wp.zeros (an allocation is zeroed by a memset on the device too)
    assert calls.as_dict() == {"launches": 2 + chunks, "memsets": 6, "scans": 1, "host_reads": 1, "syncs": 1}
    assert chunks == (2 if wp.get_device(wp_device).is_cpu else 1)
    out.numpy()
    assert calls.host_reads == 1 and wp.launch is launch and wp.array.numpy is numpy_read
