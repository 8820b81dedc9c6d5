"""Run outputs: metrics.csv, eval.csv and TensorBoard events (see docs/run-directory.md)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

METRIC_COLUMNS = ("step", "time_s", "steps_per_s", "episodes", "train_return", "train_success_rate",
                  "eval_success_rate", "eval_mean_return", "actor_loss", "critic_loss", "ent_coef", "ent_coef_loss",
                  "q_mean", "transition_model_loss", "action_model_loss", "mean_ext_reward", "mean_mc_reward",
                  "mean_total_reward", "mean_raw_kl", "mc_bound_low", "mc_bound_high")
EVAL_COLUMNS = ("step", "success_rate", "mean_return", "episodes")


def _truncate_csv(path: Path, columns: tuple[str, ...], max_step: int) -> None:
    """Keep the header and rows with step <= max_step (rows a resumed run will write again are dropped)."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(float(r["step"])) <= max_step]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)


def read_csv(path: Path) -> list[dict[str, float | None]]:
    with open(path, newline="") as f:
        return [{k: (float(v) if v not in ("", None) else None) for k, v in r.items()} for r in csv.DictReader(f)]


class RunLogger:
    def __init__(self, run_dir: Path, resume_step: int | None = None, tensorboard: bool = True):
        self.run_dir = Path(run_dir)
        self.metrics_path, self.eval_path = self.run_dir / "metrics.csv", self.run_dir / "eval.csv"
        for path, cols in ((self.metrics_path, METRIC_COLUMNS), (self.eval_path, EVAL_COLUMNS)):
            if resume_step is None or not path.exists():
                with open(path, "w", newline="") as f:
                    csv.DictWriter(f, fieldnames=cols).writeheader()
            else:
                _truncate_csv(path, cols, resume_step)
        self.tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self.tb = SummaryWriter(str(self.run_dir), purge_step=resume_step)

    def _append(self, path: Path, columns, row: dict) -> None:
        with open(path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=columns, extrasaction="ignore").writerow(
                {k: ("" if row.get(k) is None else row[k]) for k in columns})

    def log_metrics(self, row: dict) -> None:
        self._append(self.metrics_path, METRIC_COLUMNS, row)
        if self.tb is not None:
            for k, v in row.items():
                if k != "step" and v is not None and isinstance(v, (int, float)) and math.isfinite(v):
                    group = "eval" if k.startswith("eval_") else "train"
                    self.tb.add_scalar(f"{group}/{k}", v, row["step"])

    def log_eval(self, row: dict) -> None:
        self._append(self.eval_path, EVAL_COLUMNS, row)
        if self.tb is not None:
            for k in ("success_rate", "mean_return"):
                if row.get(k) is not None:  # environments without a success flag have no success rate
                    self.tb.add_scalar(f"eval/{k}", row[k], row["step"])

    def log_video(self, tag: str, frames, step: int, fps: float = 25.0) -> None:
        """An animated GIF image summary (TensorBoard shows it in the Images tab; no moviepy needed)."""
        if self.tb is None or not frames:
            return
        import tempfile

        from tensorboardX.proto.summary_pb2 import Summary

        from mcrl.video import write_video

        with tempfile.TemporaryDirectory() as d:
            path = write_video(frames, Path(d) / "v.gif", fmt="gif", fps=fps)
            data = path.read_bytes()
            from PIL import Image

            with Image.open(path) as im:
                w, h = im.size
        image = Summary.Image(height=h, width=w, colorspace=3, encoded_image_string=data)
        self.tb._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
