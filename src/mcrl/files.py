"""Files that a crash never leaves half written: the one atomic writer (`write_atomic`, `write_json`), the one CSV
row writer (`append_row`, and `write_csv` for a whole file), and the one parser of the numbers read back
(`number`).

Atomic: the bytes go to a temporary file beside the target (``.NAME.tmp``), which is flushed and fsynced, renamed
over the target (`os.replace`), and then the directory is fsynced. A reader sees the old file or the new one,
whole, and once the call returns the new one survives a power cut. A write that fails (a full disk) removes its
temporary file and leaves the target as it was. A CSV row is appended with one write and fsynced; a crash can cut
only that last row short, and the readers drop a cut row (`mcrl.run.rundir`).

Each caller keeps its file's layout: `write_json`'s options are `json.dumps`'s, plus `newline` for a file that
ends with one. This module imports nothing of mcrl, and no JAX.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable


def fsync_dir(path: str | Path) -> None:
    """Make the names in directory `path` (a rename, a new file) survive a power cut."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Replace `path` by `data` (text is written as UTF-8), atomically and durably (see the module's docstring)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()  # a full disk gets its space back
        raise
    fsync_dir(path.parent)


def write_json(path: str | Path, obj: Any, *, indent: int | None = None, sort_keys: bool = False,
               default: Callable[[Any], Any] | None = None, newline: bool = False) -> None:
    """`obj` as JSON into `path` through `write_atomic`; `indent`, `sort_keys` and `default` as `json.dumps` takes
    them, `newline`: end the file with one."""
    text = json.dumps(obj, indent=indent, sort_keys=sort_keys, default=default)
    write_atomic(path, text + "\n" if newline else text)


def _csv_text(columns: Iterable[str], rows: Iterable[dict[str, Any]], header: bool) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns))  # the excel dialect: "\r\n" after each row
    if header:
        w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def _cells(columns: Iterable[str], row: dict[str, Any]) -> dict[str, Any]:
    """`row`'s values of `columns` ("" for a missing or None value); other keys are left out."""
    return {k: ("" if row.get(k) is None else row[k]) for k in columns}


def write_csv(path: str | Path, columns: Iterable[str], rows: Iterable[dict[str, Any]] = ()) -> None:
    """A whole CSV file, the header and then `rows`, through `write_atomic` (a row with a key outside `columns` is
    an error: ValueError)."""
    write_atomic(path, _csv_text(columns, rows, header=True))


def append_row(path: str | Path, columns: Iterable[str], row: dict[str, Any]) -> None:
    """Append `row` (its values of `columns`; None is an empty cell) to the CSV `path` with one write, fsynced."""
    columns = tuple(columns)
    line = _csv_text(columns, [_cells(columns, row)], header=False)
    with open(path, "a", newline="") as f:
        f.write(line)
        f.flush()
        os.fsync(f.fileno())


def number(v: Any, finite: bool = False) -> float | None:
    """A number read from a file as a float: a CSV cell's text, or a JSON value. None for an empty cell, null, a
    boolean, and text that is not a number; with `finite`, also for NaN and the infinities."""
    if isinstance(v, str):
        try:
            x = float(v)
        except ValueError:
            return None
    elif isinstance(v, (int, float)) and not isinstance(v, bool):
        x = float(v)
    else:
        return None
    return None if finite and not math.isfinite(x) else x
