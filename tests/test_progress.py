"""Progress output (`mcrl.progress`): a tqdm bar on a terminal; in a pipe or a file a plain line every 5% and
none of the carriage-return updates a bar writes."""
import io
import subprocess
import sys

import numpy as np

from mcrl.progress import Progress


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_pipe_gets_a_plain_line_every_five_percent():
    out = io.StringIO()
    bar = Progress(1000, "train", file=out)
    for i in range(1000):
        if i == 500:
            bar.postfix("sps=12")
        bar.update(1)
    bar.close()
    text = out.getvalue()
    lines = text.splitlines()
    assert "\r" not in text and len(lines) == 20, lines
    assert lines[0].startswith("train: 50/1,000 steps (5%), ")
    assert lines[-1].startswith("train: 1,000/1,000 steps (100%), ") and lines[-1].endswith(", sps=12")


def test_a_resumed_count_and_an_early_close_in_a_pipe():
    out = io.StringIO()
    bar = Progress(1000, "train", initial=400, file=out)
    bar.set(460)
    bar.set(470)  # no new 5% step: no line
    bar.close()  # the last count is said once at the end
    assert [line.split(" steps")[0] for line in out.getvalue().splitlines()] == ["train: 460/1,000", "train: 470/1,000"]


def test_a_terminal_gets_a_bar():
    out = _Terminal()
    bar = Progress(100, "train", file=out)
    bar.update(100)
    bar.close()
    assert "\r" in out.getvalue() and "100/100" in out.getvalue()


def test_measure_in_a_pipe_writes_a_few_plain_lines(tmp_path):
    rng = np.random.default_rng(0)
    s, a = rng.normal(size=(2000, 3)), rng.normal(size=(2000, 2))
    data = tmp_path / "data.npz"
    np.savez(data, states=s, actions=a, next_states=s + 0.1 * a @ np.ones((2, 3)))
    res = subprocess.run([sys.executable, "-m", "mcrl.cli", "measure", str(data), "--max-steps", "2000",
                          "--hidden", "32", "32"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    progress = [line for line in res.stderr.splitlines() if line.startswith("fitting MC models: ")]
    assert "\r" not in res.stderr and 1 <= len(progress) <= 21, res.stderr
    assert "heldout_nll=" in progress[-1]
