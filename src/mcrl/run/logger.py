"""Run outputs as they are written: metrics.csv, eval.csv and TensorBoard events (see docs/run-directory.md)."""
from __future__ import annotations

import math
from pathlib import Path

from mcrl.run import rundir
from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS

__all__ = ["RunLogger", "METRIC_COLUMNS", "EVAL_COLUMNS"]


class RunLogger:
    def __init__(self, run_dir: Path, resume_step: int | None = None, tensorboard: bool = True,
                 metric_columns: tuple[str, ...] = METRIC_COLUMNS):
        """`metric_columns`: metrics.csv's, those of the run's reward (`rundir.metric_columns`)."""
        self.run_dir = Path(run_dir)
        self.metrics_path, self.eval_path = self.run_dir / rundir.METRICS, self.run_dir / rundir.EVAL
        self.metric_columns = metric_columns
        for path, cols in ((self.metrics_path, metric_columns), (self.eval_path, EVAL_COLUMNS)):
            if resume_step is None or not path.exists():
                rundir.start_csv(path, cols)
            else:  # rows after the checkpoint are written again by the resumed run
                rundir.truncate_rows(path, cols, resume_step)
        self.tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self.tb = SummaryWriter(str(self.run_dir), purge_step=resume_step)

    def log_metrics(self, row: dict) -> None:
        rundir.append_row(self.metrics_path, self.metric_columns, row)
        if self.tb is not None:
            for k, v in row.items():
                # eval_* repeat the last evaluation on every row: `log_eval` writes each evaluation once, at its own
                # step, as eval/<name>, so each quantity has one tag
                if k != "step" and not k.startswith("eval_") and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"train/{k}", v, row["step"])

    def log_eval(self, row: dict) -> None:
        rundir.append_row(self.eval_path, EVAL_COLUMNS, row)
        if self.tb is not None:
            for k in ("success_rate", "mean_return"):
                if row.get(k) is not None:  # environments without a success flag have no success rate
                    self.tb.add_scalar(f"eval/{k}", row[k], row["step"])

    def log_gif(self, tag: str, gif: bytes, step: int) -> None:
        """An animated GIF (already encoded) as an image summary: TensorBoard shows it in the Images tab."""
        if self.tb is None or not gif:
            return
        from tensorboardX.proto.summary_pb2 import Summary

        width, height = int.from_bytes(gif[6:8], "little"), int.from_bytes(gif[8:10], "little")  # GIF header
        image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=gif)
        self.tb._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
