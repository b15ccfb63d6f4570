"""Process-wide run control: cancellation (SIGINT / SIGTERM) and progress notes.

Cancellation
------------
One process-wide flag.  :func:`request_cancel` sets it (the signal handlers of
:func:`signal_handlers` do, and so can a library user); long loops call :func:`check`, which
raises :class:`Interrupted` (a ``KeyboardInterrupt``) once it is set.  Compiled kernels cannot
see a Python event, so they poll a small numpy array instead: :class:`StopFlag` hands one out
(registered here, so a cancel request sets it too) and can also set it when a wall-clock
deadline passes (the planners' safety caps).

The work clock
--------------
:func:`work_clock` is ``time.perf_counter()`` less every second this process spent compiling
numba kernels (a ``numba:compile`` event listener, installed on first use): a deadline on it
never counts JIT compilation, so a cold process gets the same budget as a warm one.  The
planners stop on counted work; their wall-clock caps (and :class:`StopFlag`'s deadline) are a
safety net read on this clock.

Signals reach Python code only when the main thread runs bytecode; while it waits inside a
compiled call that releases the GIL, :func:`signal_handlers` still sees the signal at once: the
C-level handler writes the signal number to a wake-up pipe that a watcher thread reads, sets
the flag (so the kernels stop) and arms a watchdog that ends the process with the right exit
code if it has not exited ``grace_s`` seconds later (with ``SKYROUTE_DEBUG_INTERRUPT=1`` it
first dumps every thread's stack on stderr: the loop that does not check the flag).  Cache entries stay consistent whatever
happens: an entry is written under ``tmp/`` and renamed into place only when complete
(:mod:`skyroute.pipeline.cache`).

Progress
--------
:func:`progress_enabled` says whether a terminal wants progress notes (the runner turns it on
with its ``progress`` argument: stderr is a tty and ``-q`` was not given); :func:`note` prints
one line on stderr when it is.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

__all__ = ["Interrupted", "StopFlag", "cancelled", "check", "clock_stops", "exit_code", "mark_reported", "note",
           "note_clock_stop", "progress",
           "progress_enabled", "request_cancel", "reset", "signal_handlers", "signal_received", "work_clock"]

RUNNING, CANCELLED, DEADLINE = 0, 1, 2   # states of a StopFlag array (element 0)

_cancel = threading.Event()
_lock = threading.Lock()
_flags: set[StopFlag] = set()
_signum: int | None = None
_progress = False


class Interrupted(KeyboardInterrupt):
    """The run was cancelled (a signal or :func:`request_cancel`)."""


def cancelled() -> bool:
    """True once a cancel was requested."""
    return _cancel.is_set()


def check() -> None:
    """Raise :class:`Interrupted` if a cancel was requested (call it between chunks of work)."""
    if _cancel.is_set():
        raise Interrupted("interrupted")


def request_cancel(signum: int | None = None) -> None:
    """Ask every running loop and kernel of this process to stop."""
    global _signum
    if signum is not None and _signum is None:
        _signum = int(signum)
    _cancel.set()
    with _lock:
        for f in _flags:
            f.array[0] = CANCELLED


def signal_received() -> int | None:
    """The first SIGINT / SIGTERM received under :func:`signal_handlers` (None if none)."""
    return _signum


def exit_code(signum: int | None = None) -> int:
    """Shell convention: 128 + signal number (SIGINT 130, SIGTERM 143); 130 without a signal."""
    s = _signum if signum is None else signum
    return 128 + int(s) if s is not None else 130


def reset() -> None:
    """Clear the cancel flag (a new command in the same process)."""
    global _signum
    _cancel.clear()
    _signum = None


# --------------------------------------------------------------------------- the work clock
_compile_s = [0.0]                   # seconds of finished compilations (all threads)
_compiling: dict[int, float] = {}    # thread id -> perf_counter() at the start of its outermost compile
_compile_depth: dict[int, int] = {}
_listener_installed = [False]


def _install_compile_listener() -> None:
    if _listener_installed[0]:     # the common case, without the lock (work_clock is on hot loops)
        return
    with _lock:
        if _listener_installed[0]:
            return
        _listener_installed[0] = True
    from numba.core import event

    class _CompileTimer(event.Listener):
        """Sums the wall time of the outermost ``numba:compile`` events of each thread."""

        def on_start(self, ev) -> None:
            tid = threading.get_ident()
            with _lock:
                d = _compile_depth.get(tid, 0)
                if d == 0:
                    _compiling[tid] = time.perf_counter()
                _compile_depth[tid] = d + 1

        def on_end(self, ev) -> None:
            tid = threading.get_ident()
            with _lock:
                d = _compile_depth.get(tid, 1) - 1
                _compile_depth[tid] = d
                if d == 0:
                    _compile_s[0] += time.perf_counter() - _compiling.pop(tid, time.perf_counter())

    event.register("numba:compile", _CompileTimer())


def compile_seconds() -> float:
    """Seconds [s] this process has spent compiling numba kernels since the work clock was first
    read (compilations still running included)."""
    _install_compile_listener()
    now = time.perf_counter()
    with _lock:
        return _compile_s[0] + sum(now - t for t in _compiling.values())


def work_clock() -> float:
    """``time.perf_counter()`` [s] less the time spent compiling numba kernels: the clock of every
    planner deadline (JIT compilation never counts against a budget)."""
    _install_compile_listener()
    return time.perf_counter() - compile_seconds()


_clock_stops = [0]      # wall-clock safety caps that stopped a search in this process


def note_clock_stop() -> None:
    """Count a search stopped by its wall-clock safety cap (:class:`StopFlag` does it; a loop
    that polls the work clock itself calls this): what a result made meanwhile holds depends on
    the machine's load, so it must not be memoised (:func:`clock_stops`)."""
    with _lock:
        _clock_stops[0] += 1


def clock_stops() -> int:
    """How many searches of this process stopped at a wall-clock safety cap so far: a caller
    compares the count before and after a computation to know whether the clock decided any of
    it (e.g. a flight replay's re-plans, before its folder is memoised)."""
    return _clock_stops[0]


class StopFlag:
    """A one-element int8 array for compiled kernels to poll: 0 running, 1 cancelled (a cancel
    request), 2 the ``deadline_s`` [s from creation, on the :func:`work_clock`: compilation
    does not count] passed.  Use as a context manager (registers it and starts / stops the
    deadline timer)."""

    def __init__(self, deadline_s: float | None = None):
        self.array = np.zeros(1, dtype=np.int8)
        self.deadline_s = deadline_s
        self._timer: threading.Timer | None = None
        self._end = math.inf
        self._closed = False

    def _arm(self, delay_s: float) -> None:
        if self._closed:
            return
        self._timer = threading.Timer(delay_s, self._expire)
        self._timer.daemon = True
        self._timer.start()

    def _expire(self) -> None:
        left = self._end - work_clock()
        if left > 1e-3:            # a compilation ran meanwhile: the deadline moved on
            self._arm(left)
            return
        if self.array[0] == RUNNING:
            self.array[0] = DEADLINE

    def __enter__(self) -> StopFlag:
        with _lock:
            _flags.add(self)
        if _cancel.is_set():
            self.array[0] = CANCELLED
        if self.deadline_s is not None and np.isfinite(self.deadline_s):
            if self.deadline_s <= 0:
                self.array[0] = DEADLINE if self.array[0] == RUNNING else self.array[0]
            else:
                self._end = work_clock() + self.deadline_s
                self._arm(self.deadline_s)
        return self

    def __exit__(self, *exc) -> None:
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
        with _lock:
            _flags.discard(self)
        if self.expired:
            note_clock_stop()

    @property
    def state(self) -> int:
        return int(self.array[0])

    @property
    def expired(self) -> bool:
        return self.state == DEADLINE

    def check(self) -> None:
        """Raise :class:`Interrupted` if this flag (or the process) was cancelled."""
        if self.state == CANCELLED:
            raise Interrupted("interrupted")
        check()


# --------------------------------------------------------------------------- signals
_handled = [0]


def _handler(signum, frame) -> None:
    _handled[0] += 1
    if _handled[0] > 1:          # a second signal: stop now
        _hard_exit(exit_code())
    request_cancel(signum)
    raise Interrupted("interrupted")


_printed = threading.Event()


def mark_reported() -> None:
    """The command layer printed "interrupted" (the watchdog then does not print it again)."""
    _printed.set()


def _hard_exit(code: int) -> None:
    if os.environ.get("SKYROUTE_DEBUG_INTERRUPT"):
        import faulthandler

        faulthandler.dump_traceback(all_threads=True)
    if not _printed.is_set():
        _printed.set()
        with contextlib.suppress(OSError):
            os.write(2, b"interrupted\n")
    os._exit(code)


def _watch(fd: int, grace_s: float, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        if not data:
            return
        for b in data:
            if b in (signal.SIGINT, signal.SIGTERM):
                request_cancel(b)
                # the main thread normally unwinds and exits well before this
                if not stop.wait(grace_s):
                    _hard_exit(exit_code())
                return


def _unraisable(previous):
    """An ``sys.unraisablehook`` that stays silent about the :class:`Interrupted` our signal
    handler raised where Python cannot propagate it (a weakref callback or ``__del__`` the signal
    happened to land in: Python would print "Exception ignored in ..." and a traceback): the
    cancel is already requested, so the command still ends with one ``interrupted`` line (its
    next check, or the watchdog).  Anything else goes to ``previous``."""
    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, Interrupted) and cancelled():
            return
        previous(unraisable)
    return hook


@contextlib.contextmanager
def signal_handlers(grace_s: float = 1.6) -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM request a cancel and raise :class:`Interrupted` in
    the main thread; if the process has not exited ``grace_s`` [s] after the signal, it exits
    with :func:`exit_code`.  A no-op outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    reset()
    _printed.clear()
    _handled[0] = 0
    r, w = os.pipe()
    os.set_blocking(w, False)
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    stop = threading.Event()
    try:
        old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except ValueError:   # pragma: no cover - not the main thread of the main interpreter
        os.close(r)
        os.close(w)
        yield
        return
    for s in old:
        signal.signal(s, _handler)
    old_hook = sys.unraisablehook
    sys.unraisablehook = _unraisable(old_hook)
    watcher = threading.Thread(target=_watch, args=(r, grace_s, stop), name="skyroute-signals", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        sys.unraisablehook = old_hook
        signal.set_wakeup_fd(old_fd)
        if _signum is None:
            stop.set()
            os.close(w)      # ends the watcher's read
            watcher.join(1.0)
            os.close(r)
        # after a signal the watcher keeps its watchdog armed until the process exits


# --------------------------------------------------------------------------- progress
def progress_enabled() -> bool:
    """True when progress notes should be printed (a terminal, not ``-q``)."""
    return _progress


@contextlib.contextmanager
def progress(enabled: bool) -> Iterator[None]:
    """Turn progress notes on or off within the block."""
    global _progress
    old, _progress = _progress, bool(enabled)
    try:
        yield
    finally:
        _progress = old


_note_sink: list = []    # a progress display taking the notes (skyroute.pipeline.progress)


def note(text: str) -> None:
    """Print one progress line on stderr when :func:`progress_enabled` (or hand it to the
    progress display that registered itself in ``_note_sink``)."""
    if _progress:
        if _note_sink and _note_sink[0](text):
            return
        print(text, file=sys.stderr, flush=True)
