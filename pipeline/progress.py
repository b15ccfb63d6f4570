"""The one progress display of every long command (stages, Monte Carlo, replay, outputs).

A command's long work is a stack of *phases* (:func:`phase`): a stage computing, the navsim
Monte Carlo, the flight replay, outputs being written.  A phase may know how far it is
(:meth:`Phase.update`: done of total, in a unit such as dask tasks or seconds of simulated
time) and what it is doing now (:meth:`Phase.note`).  The display shows them on stderr, never
on stdout (where ``-q`` commands print their JSON):

* on a terminal: one line rewritten in place with ``\\r`` (the innermost phase, its parents
  before it), redrawn at most :data:`MAX_RATE_HZ` times a second by a daemon thread, cleared
  when the last phase ends (the command's own output follows on a clean line).  Anything else
  written to ``sys.stderr`` meanwhile (a warning, a log line) first clears the line;
* not on a terminal (``-v``, or forced): one line per phase when it ends (``label: done in
  12.3 s (50/50 runs)``), and one every :data:`LINE_EVERY_S` seconds while a phase runs long.

The command line decides once per command (:func:`configure`): shown when stderr is a
terminal, or with ``-v``, never with ``-q``.  ``$SKYROUTE_PROGRESS`` overrides the terminal
test: ``1`` always (lines unless stderr is a terminal), ``0`` never (``-q`` still wins).
Library code turns it on or off for a block with :func:`shown` (``run_scenario(progress=...)``).
The display only reads the clock and the phases' counters: it never changes a result, and a
phase's update is a few attribute stores (no I/O on the caller's thread), so hot loops may
call it freely.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import IO, Any

__all__ = ["ENV", "LINE_EVERY_S", "MAX_RATE_HZ", "Phase", "close", "configure", "dask_tasks", "enabled", "note",
           "phase", "phased", "shown", "stage_phases", "wanted"]

ENV = "SKYROUTE_PROGRESS"     #: "1": always show progress (lines when stderr is no terminal); "0": never
MAX_RATE_HZ = 10.0            #: at most this many redraws of the terminal line per second
LINE_EVERY_S = 10.0           #: without a terminal: a line for a phase still running, every this many seconds [s]


class _Config:
    quiet = False
    verbose = 0
    stream: IO[str] | None = None     # None: sys.stderr (as it is when written to)
    on = False                        # the command's decision (:func:`configure`)


_cfg = _Config()
_override: list[bool] = []           # :func:`shown` blocks, innermost last
_lock = threading.RLock()


def _forced() -> bool | None:
    v = os.environ.get(ENV, "").strip().lower()
    if v in ("1", "yes", "true", "on"):
        return True
    if v in ("0", "no", "false", "off"):
        return False
    return None


def _raw_stream() -> IO[str]:
    s = _cfg.stream if _cfg.stream is not None else sys.stderr
    return s.raw if isinstance(s, _Guard) else s


def _isatty(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def wanted(quiet: bool = False) -> bool:
    """Whether a command shows progress: not with ``quiet`` (its own ``-q``) or the ``-q`` given
    to :func:`configure`; else when ``$SKYROUTE_PROGRESS`` says so, or stderr is a terminal, or
    with ``-v``."""
    if quiet or _cfg.quiet:
        return False
    forced = _forced()
    if forced is not None:
        return forced
    return _isatty(_raw_stream()) or _cfg.verbose >= 1


def configure(*, quiet: bool = False, verbose: int = 0, stream: IO[str] | None = None) -> bool:
    """The command line's verbosity (``-q``, ``-v`` count) for the command that starts; returns
    whether its progress is shown (:func:`wanted`).  ``stream``: where the display writes (default
    ``sys.stderr`` at each write; tests pass a buffer)."""
    close()
    _cfg.quiet, _cfg.verbose, _cfg.stream = bool(quiet), int(verbose), stream
    _cfg.on = wanted()
    return _cfg.on


def enabled() -> bool:
    """Whether a phase opened now is shown (the innermost :func:`shown` block, else the command's
    decision; False in a library that never called :func:`configure`)."""
    with _lock:
        return _override[-1] if _override else _cfg.on


@contextlib.contextmanager
def shown(on: bool) -> Iterator[None]:
    """Within the block, phases are shown iff ``on`` (``-q`` of :func:`configure` still wins)."""
    with _lock:
        _override.append(bool(on) and not _cfg.quiet)
    try:
        yield
    finally:
        with _lock:
            _override.pop()


class Phase:
    """One phase of the work: ``label``; ``done`` of ``total`` ``unit`` when known; a ``note``
    on what it does now.  Updating it never writes anything (the display reads it)."""

    def __init__(self, label: str, total: float | None = None, unit: str = "", detail: str = ""):
        self.label, self.total, self.unit, self.detail = label, total, unit, detail
        self.done: float | None = None
        self.t0 = time.perf_counter()
        self.source: Callable[[], tuple[float, float | None]] | None = None   # polled counts (dask)

    def update(self, done: float | None = None, total: float | None = None, detail: str | None = None) -> None:
        """Set how far the phase is (``done`` of ``total``, in its unit) and / or its note."""
        if done is not None:
            self.done = done
        if total is not None:
            self.total = total
        if detail is not None:
            self.detail = detail

    def advance(self, n: float = 1) -> None:
        """``n`` more units done."""
        self.done = (self.done or 0) + n

    def note(self, detail: str) -> None:
        """What the phase does now (e.g. the file being written)."""
        self.detail = detail

    def counts(self) -> tuple[float | None, float | None]:
        if self.source is not None:
            try:
                return self.source()
            except Exception:      # a counter being mutated by a worker thread: the last known
                pass
        return self.done, self.total

    def progress_text(self, final: bool = False) -> str:
        """``done/total unit (pct)`` (``final``: ``done unit``, or ``done/total unit`` when short)."""
        done, total = self.counts()
        unit = f" {self.unit}" if self.unit else ""
        if done is None:
            return ""
        if total and not (final and done >= total):
            pct = "" if final else f" ({min(max(done / total, 0.0), 1.0):.0%})"
            return f"{_num(done)}/{_num(total)}{unit}{pct}"
        if done == 1 and self.unit in _PLURALS:
            unit = f" {self.unit[:-1]}"
        return f"{_num(done)}{unit}"


_PLURALS = ("tasks", "runs", "files", "events")


def _num(v: float) -> str:
    return f"{v:,.0f}" if abs(v) >= 100 or float(v).is_integer() else f"{v:,.1f}"


class _Guard:
    """``sys.stderr`` while a terminal line is shown: a write first clears the line (the line
    is drawn again at the next tick)."""

    def __init__(self, raw: IO[str]):
        self.raw = raw

    def write(self, s: str) -> int:
        _display.clear_line()
        return self.raw.write(s)

    def writelines(self, lines) -> None:
        _display.clear_line()
        self.raw.writelines(lines)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.raw, name)


class _Display:
    def __init__(self) -> None:
        self.stack: list[Phase] = []
        self.live = False
        self.width = 0              # characters of the terminal line on screen (0: none)
        self.text = ""              # the terminal line on screen
        self.last = 0.0             # perf_counter() of the last line drawn
        self.thread: threading.Thread | None = None
        self.stop = threading.Event()
        self.guard: _Guard | None = None

    # ----------------------------------------------------------------- writing
    def _write(self, s: str) -> None:
        stream = _raw_stream()
        try:
            stream.write(s)
            stream.flush()
        except (OSError, ValueError):    # a closed or broken stderr: progress is not worth an error
            pass

    def clear_line(self) -> None:
        with _lock:
            if self.width:
                self._write("\r" + " " * self.width + "\r")
                self.width = 0

    def _text(self, now: float, cols: int = 10_000) -> str:
        """The terminal line, at most ``cols`` characters: every open phase, outermost first, with
        its counts, the innermost's note (shortened to fit) and its seconds."""
        head = " > ".join(" ".join(p for p in (ph.label, ph.progress_text()) if p) for ph in self.stack)
        tail = f"  {now - self.stack[-1].t0:.0f} s"
        detail = self.stack[-1].detail
        room = cols - len(head) - len(tail) - 3
        if detail and room >= 8:
            head += " - " + (detail if len(detail) <= room else detail[:room - 3] + "...")
        return (head[:max(cols - len(tail), 0)] + tail)[:cols]

    def _running(self, now: float) -> str:
        """The line, without a terminal, of a phase still running after :data:`LINE_EVERY_S`."""
        ph = self.stack[-1]
        what = "; ".join(p for p in (ph.progress_text(), ph.detail) if p)
        path = " > ".join(p.label for p in self.stack)
        return f"{path}: running for {now - ph.t0:.0f} s" + (f" ({what})" if what else "")

    def draw(self, force: bool = False) -> None:
        with _lock:
            if not self.stack:
                return
            now = time.perf_counter()
            if not force and now - self.last < 1.0 / MAX_RATE_HZ:
                return
            self.last = now
            if self.live:
                cols = max(shutil.get_terminal_size((100, 24)).columns - 1, 20)
                text = self._text(now, cols)
                if text == self.text and self.width:
                    return
                self._write("\r" + text + " " * max(self.width - len(text), 0))
                self.width, self.text = len(text), text
            else:
                self._write(self._running(now) + "\n")

    def _tick(self) -> None:
        period = 1.0 / MAX_RATE_HZ * 2        # 5 redraws a second: below the limit
        next_line = time.perf_counter() + LINE_EVERY_S
        while not self.stop.wait(period):
            if self.live:
                self.draw()
            elif time.perf_counter() >= next_line:
                self.draw(force=True)
                next_line = time.perf_counter() + LINE_EVERY_S

    # ----------------------------------------------------------------- phases
    def open(self, ph: Phase) -> None:
        with _lock:
            first = not self.stack
            self.stack.append(ph)
            if first:
                self.live = _isatty(_raw_stream())
                self.stop = threading.Event()
                if self.live and _cfg.stream is None and not isinstance(sys.stderr, _Guard):
                    self.guard = sys.stderr = _Guard(sys.stderr)
                self.thread = threading.Thread(target=self._tick, name="skyroute-progress", daemon=True)
                self.thread.start()
            if self.live:
                self.draw()

    def end(self, ph: Phase) -> None:
        with _lock:
            if ph not in self.stack:
                return
            now = time.perf_counter()
            if not self.live:
                path = " > ".join(p.label for p in self.stack[:self.stack.index(ph) + 1])
                what = "; ".join(p for p in (ph.progress_text(final=True), ph.detail) if p)
                self._write(f"{path}: done in {now - ph.t0:.1f} s" + (f" ({what})" if what else "") + "\n")
            del self.stack[self.stack.index(ph):]
            if self.stack:
                if self.live:
                    self.draw(force=True)
                return
            thread, self.thread = self.thread, None
            self.stop.set()
            self.clear_line()
            if self.guard is not None:
                if sys.stderr is self.guard:
                    sys.stderr = self.guard.raw
                self.guard = None
        if thread is not None and thread is not threading.current_thread():
            thread.join(1.0)


_display = _Display()


class _Hidden(Phase):
    """A phase that is not shown (progress off): the same methods, nothing drawn."""


@contextlib.contextmanager
def phase(label: str, total: float | None = None, unit: str = "", detail: str = "",
          on: bool | None = None) -> Iterator[Phase]:
    """A phase of the work for the ``with`` block (shown when :func:`enabled`, or ``on``)::

        with progress.phase("navsim: Monte Carlo", detail="50 runs x 1846 epochs") as ph:
            ...
            ph.update(done, total)
    """
    show = enabled() if on is None else bool(on) and not _cfg.quiet
    if not show:
        yield _Hidden(label, total, unit, detail)
        return
    ph = Phase(label, total, unit, detail)
    _display.open(ph)
    try:
        yield ph
    finally:
        _display.end(ph)


def phased(label: str) -> Callable:
    """Decorator: the function's call is a :func:`phase` ``label``."""
    def wrap(f: Callable) -> Callable:
        @functools.wraps(f)
        def inner(*args: Any, **kwargs: Any) -> Any:
            with phase(label):
                return f(*args, **kwargs)
        return inner
    return wrap


def note(detail: str) -> None:
    """What the innermost open phase does now (nothing when none is shown)."""
    with _lock:
        if _display.stack:
            _display.stack[-1].detail = detail


@contextlib.contextmanager
def dask_tasks() -> Iterator[None]:
    """Within the block, the innermost shown phase counts the tasks of the dask computations
    (the threaded / synchronous / processes schedulers' callbacks; polled by the display)."""
    with _lock:
        ph = _display.stack[-1] if _display.stack else None
    if ph is None:
        yield
        return
    from dask.callbacks import Callback

    def start_state(dsk, state) -> None:
        def counts() -> tuple[float, float]:
            done = len(state["finished"])
            return done, float(done + sum(len(state[k]) for k in ("ready", "waiting", "running")))
        ph.unit = ph.unit or "tasks"
        ph.source = counts

    with Callback(start_state=start_state):
        try:
            yield
        finally:
            if ph.source is not None:
                ph.done, ph.total = ph.counts()
                ph.source = None


class stage_phases:  # noqa: N801  (used as a context manager, like a function)
    """The phases of a pipeline run: ``[i/n] name`` for each stage computed, shown iff
    ``progress`` (:func:`shown`: phases that other code opens inside follow it too)::

        with stage_phases(progress, len(todo)) as phases:
            for i, st in enumerate(todo, 1):
                phases.start(i, st.name, st.description)   # ends the previous one
                ...
                phases.end()
    """

    def __init__(self, progress: bool, n: int):
        self.n = n
        self._shown = shown(progress)
        self._phase: contextlib.AbstractContextManager | None = None

    def __enter__(self) -> stage_phases:
        self._shown.__enter__()
        return self

    def start(self, i: int, name: str, description: str = "") -> None:
        """Stage ``name`` (the ``i``-th of ``n``) starts computing."""
        self.end()
        self._phase = phase(f"[{i}/{self.n}] {name}", detail=description)
        self._phase.__enter__()

    def end(self) -> None:
        """The stage being computed is done (its output is in the cache)."""
        ph, self._phase = self._phase, None
        if ph is not None:
            ph.__exit__(None, None, None)

    def __exit__(self, *exc: Any) -> None:
        self.end()
        self._shown.__exit__(*exc)


def _control_note(text: str) -> bool:
    """A progress note of the stages (:func:`skyroute.stages.control.note`, e.g. the planner's
    running levels): on a terminal line, the innermost phase's note (True); else printed as a line."""
    with _lock:
        if _display.live and _display.stack:
            _display.stack[-1].detail = text
            return True
    return False


def _register_note_sink() -> None:
    from skyroute.stages import control

    control._note_sink[:] = [_control_note]


_register_note_sink()


def close() -> None:
    """End every open phase (the end of a command: nothing is left on the terminal line)."""
    with _lock:
        stack = list(_display.stack)
    for ph in reversed(stack):
        _display.end(ph)
