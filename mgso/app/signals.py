"""How a run hears that it must stop: Ctrl-C (SIGINT), SIGTERM (``timeout``, ``kill``, ``docker stop``, job
schedulers) and SIGHUP (the terminal went away) all end a run the same way, as an interrupt that still writes what
was done; the exit code says which (docs/architecture.md, README "Exit codes").

- :func:`stop_signals` (around the work): SIGTERM and SIGHUP raise :class:`Terminated`, a ``KeyboardInterrupt``,
  so every ``except KeyboardInterrupt`` of the core (the system's frame loop, the mapper's final refinement) treats
  them as Ctrl-C. On a live source the first Ctrl-C only ends the stream (``end_input``): a camera has no other
  end, and a run so ended is finished as at the end of a recording.
- :func:`deferred_signals` (around writing the files that must exist): a signal is remembered, not raised; the
  block finishes its files.
- :func:`stop_signals` again around the evaluation after the essential files: a signal raises, the evaluation
  stops, and the files already written stand.

Handlers are only installed in the main thread (Python delivers signals there); elsewhere these are no-ops.

A signal that lands while a finaliser runs (a ``__del__``: Warp frees every array in one) must not raise there:
Python prints such an exception as "Exception ignored in ..." with a traceback and drops it, so the stop was lost
and the run went on. It is delivered again, once the finaliser has returned (:func:`_in_finaliser`).
"""

from __future__ import annotations

import _thread
import logging
import signal
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

__all__ = ["Terminated", "StopState", "stop_signals", "deferred_signals", "exit_code_for"]

log = logging.getLogger(__name__)

_NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}
if hasattr(signal, "SIGHUP"):
    _NAMES[signal.SIGHUP] = "SIGHUP"


class Terminated(KeyboardInterrupt):
    """A stop signal other than Ctrl-C (``signum``: SIGTERM or SIGHUP)."""

    def __init__(self, signum: int):
        super().__init__(_NAMES.get(signum, str(signum)))
        self.signum = int(signum)


class StopState:
    """The first stop signal of a run (``None``: none) and how many came."""

    def __init__(self):
        self.signum: int | None = None
        self.count = 0
        self._hold = 0
        self._pending: int | None = None
        self._redelivered = 0           # signals handed back to the handler after a finaliser (counted once)

    @contextmanager
    def held(self) -> Iterator[None]:
        """A block a stop signal must not cut in two (a frame's row in frames.csv and its count): a signal that
        arrives inside it is raised (as :func:`stop_signals` raises it) when the block ends."""
        self._hold += 1
        try:
            yield
        finally:
            self._hold -= 1
            if self._hold == 0 and self._pending is not None:
                signum, self._pending = self._pending, None
                _raise(signum)

    def record(self, signum: int) -> None:
        if self.signum is None:
            self.signum = int(signum)
        self.count += 1

    def record_exception(self, exc: BaseException) -> None:
        self.record(exc.signum if isinstance(exc, Terminated) else signal.SIGINT)

    @property
    def name(self) -> str:
        return _NAMES.get(self.signum, "") if self.signum is not None else ""


def _raise(signum: int) -> None:
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(signum)


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` (where the main thread was when the signal came) is inside a ``__del__``, at any depth:
    an exception raised there would be printed and dropped."""
    depth = 0
    while frame is not None and depth < 64:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
        depth += 1
    return False


def _redeliver(state: StopState, signum: int) -> None:
    """Hand ``signum`` to the main thread's handler again in a moment (after the finaliser it landed in)."""
    state._redelivered += 1
    t = threading.Timer(0.005, _thread.interrupt_main, (signum,))
    t.daemon = True
    t.start()


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _signals() -> list[int]:
    return list(_NAMES)


@contextmanager
def _handlers(handler) -> Iterator[None]:
    if not _main_thread():
        yield
        return
    old = {}
    for s in _signals():
        try:
            old[s] = signal.signal(s, handler)
        except (ValueError, OSError):  # not settable here
            pass
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def stop_signals(state: StopState, end_input: Callable[[], bool] | None = None) -> Iterator[StopState]:
    """SIGINT, SIGTERM and SIGHUP raise (``KeyboardInterrupt`` / :class:`Terminated`) and are recorded.

    ``end_input``: a live source's :meth:`~mgso.io.live.LiveSource.end`. Ctrl-C is how a live stream is ended, so
    the first SIGINT while it delivers only ends the input (nothing raised or recorded: the run finishes as at the
    end of a recording, final refinement and exit code 0 included); a SIGINT after that, and SIGTERM or SIGHUP at any
    time, stop as above."""

    def handler(signum, frame):
        if state._redelivered:          # the same signal, back from a finaliser: already heard and counted
            state._redelivered -= 1
        else:
            if signum == signal.SIGINT and end_input is not None and state.signum is None and end_input():
                log.warning("Ctrl-C: the live stream ends here; the odometry finishes and the map gets its final "
                            "refinement before the outputs are written (Ctrl-C again cuts the refinement short)")
                return
            state.record(signum)
        if _in_finaliser(frame):
            _redeliver(state, signum)
            return
        if state._hold:                 # raised when the held block ends (StopState.held)
            state._pending = state._pending or signum
            return
        _raise(signum)

    with _handlers(handler):
        yield state


@contextmanager
def deferred_signals(state: StopState, what: str = "writing the outputs") -> Iterator[StopState]:
    """Signals are recorded and logged, not raised, while the block runs."""

    def handler(signum, frame):
        if state._redelivered:          # one from a finaliser under stop_signals, already counted
            state._redelivered -= 1
            return
        state.record(signum)
        log.warning("%s received while %s: finishing them first", _NAMES.get(signum, signum), what)

    with _handlers(handler):
        yield state


def exit_code_for(signum: int | None) -> int:
    """128 + the signal's number, as a shell reports a process killed by it (SIGINT 130, SIGTERM 143, SIGHUP 129)."""
    return 128 + int(signum) if signum is not None else 0
