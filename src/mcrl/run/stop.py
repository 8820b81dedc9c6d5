"""Stopping training on SIGINT or SIGTERM at the next safe point, with a checkpoint.

Inside `handle`, the signal handler only records the signal. The training loop (`mcrl.run.trainer.run_loop`)
reads `requested()` once per step and saves each run at its next episode end, after that step's evaluation and
log row, as a periodic checkpoint is; mid-episode the simulator's state is not saved, so that is the first point
from which the resume is exact. When every run of the loop has saved, it raises `Stopped`, which `mcrl train`
turns into exit code 130 (SIGINT) or 143 (SIGTERM). A second signal raises KeyboardInterrupt at once: the run
keeps its last checkpoint. A sweep's workers (`second_stops_now=False`) leave the second signal to their
driver, which kills them, since a terminal's Ctrl-C reaches both and the driver also forwards it.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_first: int | None = None  # the signal that asked for the stop, while a `handle` block is active
_last: int | None = None  # the last signal received (exit code of a second one)
_depth = 0
_interactive = True


class Stopped(KeyboardInterrupt):
    """The loop stopped on a signal after saving every run; `saved` holds (run directory, checkpoint step)."""

    def __init__(self, signum: int, saved: list[tuple[Path, int]]):
        self.signum, self.saved = signum, saved
        super().__init__(f"stopped by {signal.Signals(signum).name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def requested() -> int | None:
    """The signal that asked for a stop, or None."""
    return _first


def request(signum: int = signal.SIGTERM) -> None:
    """Ask for a stop as a signal would (from another thread: a Ray task told to stop by its driver)."""
    global _first
    if _first is None:
        _first = signum


def exit_code() -> int:
    """128 + the last signal received (130 when none was: an interrupt from Python itself)."""
    return 128 + (_last or signal.SIGINT)


def announcement(step: int) -> str | None:
    """The line that says a requested stop was noticed at `step` (None in a sweep's worker: its driver speaks)."""
    if not _interactive or _first is None:
        return None
    return (f"mcrl: {signal.Signals(_first).name} at step {step:,}: saving a checkpoint at the episode's end, then "
            "stopping (press Ctrl-C again to stop at once and keep only the last checkpoint)")


def _handler(second_stops_now: bool):
    def on_signal(signum, frame):
        global _first, _last
        _last = signum
        if _first is None:
            _first = signum
        elif second_stops_now:
            raise KeyboardInterrupt  # the run keeps its last checkpoint

    return on_signal


@contextlib.contextmanager
def handle(second_stops_now: bool = True):
    """Within the block, SIGINT and SIGTERM ask for a stop (`requested`) instead of ending the process.

    Only in the main thread (elsewhere Python cannot set handlers: `request` still works), and never over a signal
    this process was started ignoring (`nohup`, a shell's background job). Nested blocks keep the outer one's."""
    global _first, _depth, _interactive
    outer = _depth == 0
    old = {}
    if outer and threading.current_thread() is threading.main_thread():
        for sig in SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                old[sig] = signal.signal(sig, _handler(second_stops_now))
    if outer:
        _interactive = second_stops_now
    _depth += 1
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        _depth -= 1
        if outer:
            _first, _interactive = None, True
