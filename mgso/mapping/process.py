"""The mapper in a process of its own: real time without sharing the interpreter lock with the odometry.

In real time the odometry has to keep the camera's frame rate while the map trains as fast as it can. As two
threads of one process they fight over the interpreter lock, the cores and (on CUDA) one stream. A
:class:`MapperProcess` runs the same :class:`~mgso.mapping.mapper.Mapper` in a spawned process (the same on Linux,
macOS and Windows) with its own interpreter, its own Warp context (and CUDA stream) and its own share of the cores:

::

    main process                                         mapper process (spawned)
    odometry -> MapperProcess.submit(msg) --messages-->  Mapper._run: apply messages, train, repeat
                 keyframe images -> shared-memory ring --> copied out, the slot handed back
                 request_snapshot / request_render ----->  served between two steps
    receiver thread <--- MapUpdate, snapshots, renders --  (Observer.on_map_updated from that thread)
                    <--- the final MapState -------------  after Stop (or the interrupt)
    MapperProcess.stop() -> Mapper.restored(state): renders, PLY, refined trajectory, as in one process

**Never waiting on the map.** Messages go over a bounded queue (``mapping.mapper.queue_size``); images over a ring
of shared-memory slots (blocks of ``system.image_slots``; the ring grows by a block when every slot waits for the
mapper, up to as many slots as the queue holds), not as pickled copies. Only a full queue or ring makes the odometry
wait, and each wait is counted (``MapperStats.queue_waits``, ``queue_wait_seconds``) as in one process.

**Its priority.** While the camera runs the process is a background one (:func:`lower_priority`): on Linux
``SCHED_IDLE`` (``system.mapper_sched_idle``), so that the odometry's tracking thread gets a core the moment it
wakes, and the niceness ``system.mapper_nice``; for the final refinement the normal policy again where the system
allows it (:func:`restore_priority`). ``MapperStats.priority`` / ``final_priority`` say what it ran at.

**Stops.** The mapper process ignores Ctrl-C, SIGTERM and SIGHUP: a terminal's Ctrl-C reaches the whole process
group, and the main process decides how the run ends. :meth:`MapperProcess.stop` sends ``Stop``; with
``refine=False`` (an interrupt) it also sets a shared event that ends training at the next step, so the process
applies what is queued and hands its map back at once. A second interrupt while the main process waits for the final
refinement propagates to the caller, which calls ``stop(refine=False)`` again (as :mod:`mgso.system` does). An error
in the mapper process is sent back with the map of what was done; a mapper process that dies (killed) is an error
naming its exit code. A mapper process whose parent is gone (killed with SIGKILL) notices within half a second and
exits: no orphan keeps a core busy.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import os
import queue
import signal
import sys
import threading
import time
import traceback
import types
from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

from mgso.config import Config
from mgso.mapping.mapper import MapperError, MapperStats, MapState
from mgso.messages import KeyframeMessage, LoopCorrection, MapperMessage, PointsMessage, PoseUpdate, Stop
from mgso.mapping.snapshot import MapSnapshot, SnapshotBoard
from mgso.observers import Observer

__all__ = ["MapperProcess", "lower_priority", "restore_priority", "split_threads"]

log = logging.getLogger(__name__)

_PARENT_CHECK_S = 0.5       # how often the mapper process looks whether its parent is still there


def split_threads(odometry_threads: int, mapper_threads: int, cores: int | None = None) -> tuple[int, int]:
    """The CPU threads of the odometry's and the mapper's kernel launches when they run side by side: a setting of 0
    means automatic (the mapper half the cores, the odometry the rest, each at least one)."""
    cores = int(cores if cores is not None else (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                                 else (os.cpu_count() or 1)))
    m = int(mapper_threads) if mapper_threads > 0 else max(1, cores // 2)
    o = int(odometry_threads) if odometry_threads > 0 else max(1, cores - m)
    return o, m


# -------------------------------------------------------------------------------------- shared-memory images
@dataclass(frozen=True)
class _WireKeyframe:
    """A :class:`KeyframeMessage` on its way: its image and mask in slot ``slot`` of the ring ``ring``, the rest
    of its fields as they are."""

    ring: str
    slot: int
    slot_bytes: int
    image_shape: tuple
    mask_shape: tuple | None
    fields: dict


class _ImageRing:
    """The main process's side of the keyframe images' ring: ``slots`` slots of ``slot_bytes`` in one shared-memory
    block; a slot is free again when the mapper process sends its number back."""

    def __init__(self, slots: int, slot_bytes: int):
        self.slots = int(slots)
        self.slot_bytes = int(slot_bytes)
        self.shm = shared_memory.SharedMemory(create=True, size=self.slots * self.slot_bytes)
        self.free = list(range(self.slots))

    def fits(self, msg: KeyframeMessage) -> bool:
        need = msg.image.size * 4 + (0 if msg.mask is None else msg.mask.size * 4)
        return need <= self.slot_bytes

    def write(self, slot: int, msg: KeyframeMessage) -> _WireKeyframe:
        base = slot * self.slot_bytes
        img = np.ndarray(msg.image.shape, np.float32, buffer=self.shm.buf, offset=base)
        img[...] = msg.image
        mask_shape = None
        if msg.mask is not None:
            m = np.ndarray(msg.mask.shape, np.float32, buffer=self.shm.buf, offset=base + msg.image.size * 4)
            m[...] = msg.mask
            mask_shape = tuple(msg.mask.shape)
            del m
        del img
        fields = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg) if f.name not in ("image", "mask")}
        return _WireKeyframe(self.shm.name, slot, self.slot_bytes, tuple(msg.image.shape), mask_shape, fields)

    def close(self) -> None:
        try:
            self.shm.close()
            self.shm.unlink()
        except (FileNotFoundError, OSError):
            pass


class _WireQueue:
    """The mapper process's view of the message queue: ``get`` / ``get_nowait`` as :class:`queue.Queue`, with
    keyframe images copied out of the ring (the slot then goes back to the main process)."""

    def __init__(self, messages, released):
        self._q = messages
        self._released = released
        self._rings: dict[str, shared_memory.SharedMemory] = {}

    def _decode(self, item):
        if not isinstance(item, _WireKeyframe):
            return item
        shm = self._rings.get(item.ring)
        if shm is None:
            shm = self._rings[item.ring] = shared_memory.SharedMemory(name=item.ring)
        base = item.slot * item.slot_bytes
        n_img = int(np.prod(item.image_shape))
        image = np.ndarray(item.image_shape, np.float32, buffer=shm.buf, offset=base).copy()
        mask = None
        if item.mask_shape is not None:
            mask = np.ndarray(item.mask_shape, np.float32, buffer=shm.buf, offset=base + n_img * 4).copy()
        self._released.put((item.ring, item.slot))
        return KeyframeMessage(image=image, mask=mask, **item.fields)

    def get_nowait(self):
        return self._decode(self._q.get_nowait())

    def get(self, block: bool = True, timeout: float | None = None):
        return self._decode(self._q.get(block, timeout))

    def qsize(self) -> int:
        try:
            return self._q.qsize()
        except NotImplementedError:      # macOS
            return 0

    def close(self) -> None:
        for shm in self._rings.values():
            try:
                shm.close()
            except (BufferError, OSError):
                pass
        self._rings.clear()


# ------------------------------------------------------------------------------------- the mapper process
class _ForwardingBoard(SnapshotBoard):
    """The mapper process's board: what it publishes goes to the main process."""

    def __init__(self, events):
        super().__init__()
        self._events = events
        self.render_ticket = 0          # the main process's ticket of the render asked last

    def publish_snapshot(self, snap: MapSnapshot) -> None:
        self._events.put(("snapshot", snap))

    def publish_render(self, ticket: int, image: np.ndarray) -> None:
        self._events.put(("render", self.render_ticket, image))


class _EventObserver(Observer):
    def __init__(self, events):
        self._events = events

    def on_map_updated(self, stats) -> None:
        self._events.put(("update", stats))


def _own_threads() -> list[int] | None:
    """The task ids of this process's threads (Linux: a thread's priority is its own), None elsewhere."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except (OSError, ValueError):
        return None


def lower_priority(nice: int, idle: bool) -> str:
    """Make this process a background one for a real-time run, and say what it got: ``"SCHED_IDLE"``, ``"nice
    +N"`` or ``"normal"``.

    ``nice``: a niceness increment (POSIX), for every thread of the process (on Linux each thread has its own;
    threads started later inherit it). ``idle`` (Linux): every thread under the ``SCHED_IDLE`` policy as well.
    Such a thread runs only on a core nothing else wants, and the scheduler counts a core that runs only idle
    threads as free when it places a waking thread, so the odometry's tracking thread takes it at once. A niceness
    alone does not do that: the niced mapper keeps its core, and the tracking thread waits in the run queue behind
    the odometry's own mapping thread (on a 2-core machine 10-15 ms of every frame, docs/mgso.md)."""
    got = "normal"
    tids = _own_threads()
    if nice and hasattr(os, "nice"):
        try:
            if tids is None:
                os.nice(int(nice))
            else:
                for tid in tids:
                    os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + int(nice))
            got = f"nice +{int(nice)}"
        except OSError:
            log.debug("the mapper process could not lower its niceness", exc_info=True)
    if idle and tids is not None and hasattr(os, "SCHED_IDLE"):
        try:
            for tid in tids:
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            got = "SCHED_IDLE"
        except OSError:
            log.debug("the mapper process could not take SCHED_IDLE", exc_info=True)
    return got


def restore_priority(got: str, nice: int) -> str:
    """After the camera: the policy of :func:`lower_priority` back to the normal one (the niceness stays), so that
    the final refinement is not starved by whatever else the machine runs. Linux allows it only to a privileged
    process or one whose ``RLIMIT_NICE`` admits the niceness; otherwise the process stays ``SCHED_IDLE`` (on a
    machine with nothing else to run it still gets every core). Returns what the refinement runs at."""
    if got != "SCHED_IDLE":
        return got
    try:
        for tid in _own_threads() or ():
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        return got
    return f"nice +{int(nice)}" if nice else "normal"


def _mapper_main(config: Config, device: str, threads: int, nice: int, idle: bool, messages, released, requests,
                 events, interrupt, stream_ended) -> None:
    """The mapper process (spawned): a :class:`Mapper` draining ``messages``, then its :class:`MapState` back."""
    for sig in (signal.SIGINT, getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)      # the main process decides how the run ends
    priority = lower_priority(nice, idle)
    from mgso.mapping.mapper import Mapper
    from mgso_kernels import runtime

    mapper = None
    wire = _WireQueue(messages, released)
    try:
        dev = runtime.init(device, threads=threads, blas_threads=1)
        board = _ForwardingBoard(events)
        parent = mp.parent_process()
        last_check = [time.monotonic()]

        def before_final() -> None:
            mapper.stats.final_priority = restore_priority(priority, nice)

        def hook() -> None:
            while True:
                try:
                    req = requests.get_nowait()
                except queue.Empty:
                    break
                if req[0] == "snapshot":
                    SnapshotBoard.request_snapshot(board, req[1])
                elif req[0] == "render":
                    board.render_ticket = req[1]
                    SnapshotBoard.request_render(board, req[2], req[3], req[4])
            if interrupt.is_set():
                mapper.interrupt()
            if stream_ended.is_set():
                mapper.stream_ended.set()         # the rest of the queue on every core (Mapper._end_of_stream)
            now = time.monotonic()
            if now - last_check[0] > _PARENT_CHECK_S:
                last_check[0] = now
                if parent is not None and not parent.is_alive():
                    os._exit(3)                       # the run is gone: nobody would read the map

        # the messages and images from the main process, a board that forwards watchers' requests, the pipes
        # polled at every safe point; after an interrupt the messages still in the pipe are applied until Stop; the
        # odometry has finished when Stop comes: every core refines (final_threads 0) at normal priority
        mapper = Mapper(config, device=dev, observer=_EventObserver(events), messages=wire, board=board,
                        safe_point_hook=hook, drain_until_stop=True, final_threads=0, before_final=before_final)
        mapper.stats.priority = priority
        mapper.load_kernels()             # before "ready": the camera plays after it (a compile takes seconds)
        events.put(("ready",))
        cpu0 = time.process_time()
        err = mapper.run_here()           # Mapper's real-time loop, in this process's main thread
        mapper.stats.cpu_seconds = time.process_time() - cpu0    # all its threads (split kernel launches)
        if err is not None:
            events.put(("error", f"{type(err).__name__}: {err}",
                        "".join(traceback.format_exception(type(err), err, err.__traceback__))))
        events.put(("final", mapper.export_state()))
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the main process
        events.put(("error", f"{type(exc).__name__}: {exc}", traceback.format_exc()))
        if mapper is not None:
            try:
                events.put(("final", mapper.export_state()))
            except Exception:  # noqa: BLE001 - the error above is what counts
                pass
    finally:
        wire.close()
        events.close()
        events.join_thread()
        released.close()
        released.join_thread()


# ------------------------------------------------------------------------------------------ the main side
class MapperProcess:
    """A :class:`~mgso.mapping.mapper.Mapper` in a spawned process, with the mapper's interface (see the module
    doc): :meth:`start`, :meth:`submit`, :meth:`stop`, ``stats``, the watchers' requests, and after :meth:`stop`
    everything a finished mapper offers (``gmap``, ``views``, ``render``, ``refined_trajectory``, ...), from
    :meth:`Mapper.restored`.

    ``threads``: CPU threads of the mapper's kernel launches; ``nice``: its niceness increment (POSIX); ``idle``:
    the process under ``SCHED_IDLE`` while the camera runs (Linux; :func:`lower_priority`); ``image_slots``: slots of
    the keyframe images' ring; ``start_timeout``: seconds to wait for the process."""

    def __init__(self, config: Config, *, device: str | None = None, observer: Observer | None = None,
                 threads: int = 1, nice: int = 0, idle: bool = False, image_slots: int = 8):
        self.config = config
        self.device = device or "cpu"
        self.observer = observer or Observer()
        self.threads = int(threads)
        self.nice = int(nice)
        self.idle = bool(idle)
        self.image_slots = max(1, int(image_slots))
        self.stats = MapperStats()
        self.board = SnapshotBoard()
        self._ctx = mp.get_context("spawn")
        self._proc = None
        self._blocks: dict[str, _ImageRing] = {}       # the ring: blocks of image_slots slots, by name
        self._free: list[tuple[str, int]] = []
        self._done = threading.Event()
        self._ready = threading.Event()
        self._error: str | None = None
        self._error_trace = ""
        self._state: MapState | None = None
        self._local = None
        self._stop_sent = False
        self._stopped = False
        self._receiver: threading.Thread | None = None

    # ------------------------------------------------------------------------------------------ lifetime
    @property
    def running(self) -> bool:
        return self._proc is not None and not self._done.is_set()

    def start(self) -> None:
        """Spawn the mapper process (it imports mgso and starts Warp there: about a second, or the kernel
        compilation on a first run; messages submitted meanwhile wait in the queue)."""
        if self._proc is not None:
            raise RuntimeError("MapperProcess.start: already started")
        ctx = self._ctx
        self._messages = ctx.Queue(maxsize=self.config.mapping.mapper.queue_size)
        self._released = ctx.Queue()
        self._requests = ctx.Queue()
        self._events = ctx.Queue()
        self._interrupt = ctx.Event()
        self._stream_ended = ctx.Event()
        self._proc = ctx.Process(
            target=_mapper_main, name="mgso-mapper",
            args=(self.config, self.device, self.threads, self.nice, self.idle, self._messages, self._released,
                  self._requests, self._events, self._interrupt, self._stream_ended),
            daemon=True)
        # The child needs nothing of the caller's main module (the target and its arguments are mgso's): do not let
        # spawn run it again there, which would rerun a user's script that has no `if __name__ == "__main__"` guard
        # (and cost its imports on every start).
        main = sys.modules.get("__main__")
        sys.modules["__main__"] = types.ModuleType("__main__")
        try:
            self._proc.start()
        finally:
            if main is not None:
                sys.modules["__main__"] = main
        self._receiver = threading.Thread(target=self._receive, name="mgso-mapper-events", daemon=True)
        self._receiver.start()

    def wait_ready(self, timeout: float = 120.0) -> bool:
        """Wait until the mapper's process has started (imported mgso, started Warp, made its mapper), it has
        failed, or ``timeout`` seconds passed; whether it is ready. Messages submitted before wait in the queue, so
        this is only to keep the start-up off the odometry's first frames."""
        t0 = time.perf_counter()
        while not self._ready.wait(0.05):
            if self._done.is_set() or time.perf_counter() - t0 > timeout:
                return False
        return True

    def _receive(self) -> None:
        """The main process's receiver: the mapper process's events, until its final state (or its death)."""
        try:
            while True:
                try:
                    kind, *rest = self._events.get(timeout=0.2)
                except queue.Empty:
                    if not self._proc.is_alive():
                        # its last events may still be in the pipe
                        try:
                            kind, *rest = self._events.get(timeout=1.0)
                        except queue.Empty:
                            if self._error is None:
                                self._error = (f"the mapper process ended without its map (exit code "
                                               f"{self._proc.exitcode})")
                            return
                    else:
                        continue
                if kind == "ready":
                    self._ready.set()
                elif kind == "update":
                    try:
                        self.observer.on_map_updated(rest[0])
                    except Exception:  # noqa: BLE001 - an observer must not stop the run
                        log.exception("an observer failed in on_map_updated")
                elif kind == "snapshot":
                    self.board.publish_snapshot(rest[0])
                elif kind == "render":
                    self.board.publish_render(rest[0], rest[1])
                elif kind == "error":
                    self._error, self._error_trace = rest[0], rest[1]
                    log.error("the mapper process failed: %s\n%s", rest[0], rest[1])
                elif kind == "final":
                    self._state = rest[0]
                    return
        finally:
            self._done.set()

    # ------------------------------------------------------------------------------------------ messages
    def submit(self, msg: MapperMessage) -> None:
        """Put ``msg`` on the queue (a keyframe's image into the ring). A full queue or ring makes the caller wait
        (counted); raises :class:`MapperError` if the mapper process has failed or ended."""
        if not isinstance(msg, (KeyframeMessage, PoseUpdate, PointsMessage, LoopCorrection, Stop)):
            raise TypeError(f"MapperProcess.submit: expected a mapper message, got {type(msg).__name__}")
        if self._proc is None:
            raise RuntimeError("MapperProcess.submit: call start() first")
        self._raise_if_failed()
        item = msg
        waited = 0.0
        if isinstance(msg, KeyframeMessage):
            item, waited = self._to_wire(msg)
        try:
            depth = self._messages.qsize()
        except NotImplementedError:      # macOS
            depth = 0
        self.stats.max_queue_depth = max(self.stats.max_queue_depth, depth + 1)
        try:
            self._messages.put_nowait(item)
        except queue.Full:
            t0 = time.perf_counter()
            log.warning("mapper queue full (%d messages): the odometry waits for the map",
                        self.config.mapping.mapper.queue_size)
            while True:
                try:
                    self._messages.put(item, timeout=0.1)
                    break
                except queue.Full:
                    self._check_alive("waited for queue room")
            waited += time.perf_counter() - t0
        if waited > 0:
            self.stats.queue_waits += 1
            self.stats.queue_wait_seconds += waited

    def _to_wire(self, msg: KeyframeMessage):
        """The keyframe into a free slot of the ring. When every slot waits for the mapper, the ring grows by a
        block (the odometry does not wait), up to as many slots as the queue holds messages; beyond that the
        odometry waits for a slot (counted as a queue wait)."""
        need = msg.image.size * 4 + msg.image.shape[0] * msg.image.shape[1] * 4
        if self._blocks and not next(iter(self._blocks.values())).fits(msg):
            log.debug("keyframe %d does not fit the image ring: sent pickled", msg.keyframe_id)
            return msg, 0.0
        self._collect_slots(block=False)
        waited = 0.0
        if not self._free:
            slots = sum(b.slots for b in self._blocks.values())
            if slots < max(self.image_slots, self.config.mapping.mapper.queue_size):
                block = _ImageRing(self.image_slots, need)
                self._blocks[block.shm.name] = block
                self._free += [(block.shm.name, k) for k in range(block.slots)]
                self.stats.image_blocks = len(self._blocks)
                if len(self._blocks) > 1:
                    log.debug("the mapper is %d keyframe images behind: the image ring grows to %d slots", slots,
                              slots + block.slots)
            else:
                t0 = time.perf_counter()
                log.warning("all %d image slots are waiting for the mapper: the odometry waits for the map", slots)
                while not self._free:
                    self._collect_slots(block=True)
                    if not self._free:
                        self._check_alive("waited for an image slot")
                waited = time.perf_counter() - t0
        name, slot = self._free.pop(0)
        return self._blocks[name].write(slot, msg), waited

    def _collect_slots(self, block: bool) -> None:
        try:
            item = self._released.get(timeout=0.1) if block else self._released.get_nowait()
        except queue.Empty:
            return
        while True:
            self._free.append((item[0], int(item[1])))
            try:
                item = self._released.get_nowait()
            except queue.Empty:
                return

    def _check_alive(self, what: str) -> None:
        if self._done.is_set() or not self._proc.is_alive():
            self._raise_if_failed()
            raise MapperError(f"the mapper process stopped while the odometry {what}")

    def _raise_if_failed(self) -> None:
        if self._error is not None and not self._stopped:
            raise MapperError(f"the mapper process failed: {self._error}")

    # ------------------------------------------------------------------------------------------ stopping
    def stop(self, refine: bool = True, timeout: float | None = None) -> MapperStats:
        """End the stream: ``Stop`` (``refine``: the final refinement), wait for the map, restore it here (see the
        class doc). Idempotent; an interrupt while waiting propagates (call ``stop(refine=False)`` again to end the
        refinement). Raises :class:`MapperError` when the mapper process failed."""
        if self._stopped:
            if self._error is not None:
                raise MapperError(f"the mapper process failed: {self._error}")
            return self.stats
        if self._proc is None:
            raise RuntimeError("MapperProcess.stop: the process was never started")
        if not refine:
            self._interrupt.set()
        self._stream_ended.set()        # before Stop: what is still queued is applied on every core
        if not self._stop_sent and not self._done.is_set():
            self._stop_sent = True
            try:
                self.submit(Stop(refine))
            except MapperError:
                pass                    # it is gone; its error is below
        t0 = time.perf_counter()
        while not self._done.wait(0.05):
            if timeout is not None and time.perf_counter() - t0 > timeout:
                self._kill()
                self._finish_stop()
                raise MapperError(f"the mapper process did not stop within {timeout} s (killed)")
        self._finish_stop()
        if self._error is not None:
            raise MapperError(f"the mapper process failed: {self._error}")
        return self.stats

    def _finish_stop(self) -> None:
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._kill()
        for block in self._blocks.values():
            block.close()
        for q in (self._messages, self._released, self._requests):
            q.cancel_join_thread()
            q.close()
        if self._state is not None:
            from mgso.mapping.mapper import Mapper

            local_stats = self.stats
            self._local = Mapper.restored(self.config, self._state, device=self.device)
            st = self._local.stats
            st.queue_waits = local_stats.queue_waits
            st.queue_wait_seconds = local_stats.queue_wait_seconds
            st.max_queue_depth = local_stats.max_queue_depth
            st.image_blocks = local_stats.image_blocks
            self.stats = st
        self._stopped = True

    def _kill(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)

    def close(self) -> None:
        """Kill the process (if alive) and free the ring; for cleanup after an error."""
        if self._proc is not None and not self._stopped:
            self._interrupt.set()
            self._kill()
            self._done.wait(2.0)
            self._finish_stop()

    # ------------------------------------------------------------------------------------------ watchers
    def request_snapshot(self, max_gaussians: int | None = None) -> None:
        """Ask the mapper process for a :class:`MapSnapshot` (never waits; see :mod:`mgso.mapping.snapshot`)."""
        if self._local is not None:
            self._local.request_snapshot(max_gaussians)
            self.board.publish_snapshot(self._local.latest_snapshot())
            return
        if max_gaussians is not None and int(max_gaussians) < 1:
            raise ValueError(f"request_snapshot: max_gaussians must be >= 1 or None, got {max_gaussians}")
        if self.running:
            self._requests.put(("snapshot", None if max_gaussians is None else int(max_gaussians)))

    def latest_snapshot(self) -> MapSnapshot | None:
        return self.board.latest_snapshot()

    def request_render(self, camera, world_to_cam, exposure=None) -> int:
        """Ask for a render of the map (never waits); returns its ticket (:meth:`latest_render`)."""
        ticket = self.board.request_render(camera, world_to_cam, exposure)
        self.board.take_requests()        # this side only numbers the tickets
        if self._local is not None:
            self.board.publish_render(ticket, self._local.render(camera, np.asarray(world_to_cam, np.float64),
                                                                 exposure=exposure))
        elif self.running:
            self._requests.put(("render", ticket, camera, np.asarray(world_to_cam, np.float64), exposure))
        return ticket

    def latest_render(self) -> tuple[int, np.ndarray] | None:
        return self.board.latest_render()

    # ------------------------------------------------------------------------------------------ the result
    def __getattr__(self, name: str):
        # everything else a finished mapper offers (gmap, views, render, refined_trajectory, exposure_for, ...)
        if name.startswith("_"):
            raise AttributeError(name)
        local = self.__dict__.get("_local")
        if local is None:
            raise AttributeError(f"MapperProcess.{name}: the map is in the mapper process until stop() brings it "
                                 "back")
        return getattr(local, name)
