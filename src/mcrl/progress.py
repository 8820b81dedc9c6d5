"""Progress output of the commands (train, measure, sweep, eval, render): a tqdm bar on a terminal; in a pipe
or a file, a plain line every few percent and one at the end, so a log holds a few readable lines instead of
hundreds of carriage-return updates.
"""
from __future__ import annotations

import math
import sys
import time
from typing import IO

EVERY = 0.05  # a line per 5% of the work in a pipe or file


def is_terminal(stream: IO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or closed
        return False


def duration(seconds: float) -> str:
    """1h02m03s, 4m05s or 6s."""
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s" if s >= 3600 else (
        f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s")


class Progress:
    """Progress through `total` units of work, written to `file` (default stderr)."""

    def __init__(self, total: int, desc: str, unit: str = "step", initial: int = 0, file: IO | None = None,
                 every: float = EVERY):
        self.file = file if file is not None else sys.stderr
        self.total, self.desc, self.unit, self.n = int(total), desc, unit, int(initial)
        self._post = ""
        self._tqdm = None
        if is_terminal(self.file):
            from tqdm import tqdm

            self._tqdm = tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True,
                              smoothing=0.05, mininterval=1.0, file=self.file)
            return
        self._t0, self._n0 = time.monotonic(), self.n
        self._stride = max(1, math.ceil(self.total * every))
        self._next = (self.n // self._stride + 1) * self._stride
        self._printed = self.n

    def update(self, n: int = 1) -> None:
        self.set(self.n + n)

    def set(self, n: int) -> None:
        """The work done so far is `n` units."""
        if self._tqdm is not None:
            self._tqdm.update(n - self._tqdm.n)  # tqdm redraws at most once a second
        elif n >= self._next or (n >= self.total > self._printed):
            self._line(n)
            self._next = (n // self._stride + 1) * self._stride
        self.n = n

    def postfix(self, text: str) -> None:
        """A short status shown beside the count (the bar's postfix; the next line's tail)."""
        self._post = text
        if self._tqdm is not None:
            self._tqdm.set_postfix_str(text, refresh=False)

    def write(self, msg: str, file: IO | None = None) -> None:
        """A line of output that does not break the bar."""
        if self._tqdm is not None:
            self._tqdm.write(msg, file=file)
        else:
            print(msg, file=file or self.file, flush=True)

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
        elif self.n != self._printed:
            self._line(self.n)

    def _line(self, n: int) -> None:
        elapsed = time.monotonic() - self._t0
        pct = 100.0 * n / self.total if self.total else 100.0
        rate = f", {(n - self._n0) / elapsed:.1f} {self.unit}s/s" if elapsed > 0 and n > self._n0 else ""
        post = f", {self._post}" if self._post else ""
        print(f"{self.desc}: {n:,}/{self.total:,} {self.unit}s ({pct:.0f}%), {duration(elapsed)}{rate}{post}",
              file=self.file, flush=True)
        self._printed = n


def progress(total: int, desc: str, unit: str = "step", initial: int = 0, enabled: bool = True,
             file: IO | None = None) -> Progress | None:
    """A `Progress`, or None when progress output is off (`--no-progress`)."""
    return Progress(total, desc, unit, initial, file) if enabled else None
