"""MLflow tracking of a sweep (``mcrl sweep --tracking``).

One MLflow experiment per sweep, one MLflow run per mcrl run (named like the run), logged by the
sweep driver when the run finishes: params = the resolved config, metrics = one name per metric
(:func:`metric_series`: metrics.csv's columns as they are named in its header, the evaluations from
eval.csv as ``eval/success_rate`` and ``eval/mean_return``) with their env steps, artifacts = the run's
learning-curve plot (``mcrl.analysis.plots.plot_run``), its config.json and the two CSVs.

Default store: SQLite inside the experiment directory (``sqlite:////abs/EXP/mlflow.db``, artifacts
under ``EXP/mlartifacts``); browse it with ``mlflow ui --backend-store-uri sqlite:////abs/EXP/mlflow.db``.
Any other MLflow tracking URI (a server ``http://host:5000``, a database) works with ``--tracking-uri``;
it is probed before the sweep writes anything.
"""
from __future__ import annotations

import csv
import json
import logging
import math
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from mcrl.errors import MCRLError
from mcrl.run import rundir
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import patched_environ

RUN_TAG = "mcrl.run_name"
SWEEP_TAG = "mcrl.sweep_id"
_BATCH = 1000  # MLflow's limit of metrics per log_batch call
_PARAM_BATCH = 100


def default_uri(exp: Path) -> str:
    return f"sqlite:///{Path(exp).absolute() / 'mlflow.db'}"


def ui_command(uri: str) -> str:
    """How to look at the store: the `mlflow ui` command of a local store, or the server's address."""
    if uri.startswith(("http://", "https://")):
        return f"open {uri}"
    return f"mlflow ui --backend-store-uri {uri}"


def _import_mlflow():
    try:
        import mlflow  # noqa: F401
        from mlflow import MlflowClient
    except ImportError:
        raise MCRLError("--tracking needs MLflow: pip install 'mcrl[sweep]' (or mlflow)") from None
    for name in ("alembic", "mlflow"):  # the store's schema migrations log at INFO on first use
        logging.getLogger(name).setLevel(logging.WARNING)
    return MlflowClient


def _no_retries():
    """MLflow retries HTTP requests with backoff for minutes; a probe must answer in seconds."""
    return patched_environ({"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "MLFLOW_HTTP_REQUEST_TIMEOUT": "10"})


def _first_line(e: BaseException) -> str:
    s = str(e).strip()
    return f"{type(e).__name__}: {s.splitlines()[0][:200]}" if s else type(e).__name__


def _param_value(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v)


def _finite(v: float | None) -> float | None:
    """A CSV cell as MLflow takes it: NaN and infinities are left out, like empty cells."""
    return v if v is not None and math.isfinite(v) else None


class Tracker:
    """Logs finished runs of one sweep to MLflow. `check` probes (writes nothing); `open` creates the
    experiment; `log_run` logs one run; `is_logged` tells whether a run is already there."""

    def __init__(self, uri: str, default_store: bool):
        self.uri = uri
        self.default_store = default_store
        self.client = None
        self.experiment_id: str | None = None
        self.experiment_name: str | None = None
        self.sweep_id: str | None = None

    @classmethod
    def check(cls, uri: str | None, exp: Path) -> "Tracker":
        """Probe the tracking URI before anything is written; None = the SQLite store inside `exp`."""
        client_cls = _import_mlflow()
        if uri is None:
            return cls(default_uri(exp), True)
        uri = uri.strip()
        parsed = urlparse(uri)
        scheme = parsed.scheme.lower()
        if scheme in ("http", "https"):
            host = parsed.hostname
            if not host:
                raise MCRLError(f"--tracking-uri {uri}: give http://HOST:PORT of an MLflow tracking server")
            port = parsed.port or (443 if scheme == "https" else 80)
            try:
                with socket.create_connection((host, port), timeout=3.0):
                    pass
            except OSError as e:
                raise MCRLError(f"MLflow tracking server {uri} cannot be reached ({type(e).__name__}: "
                                f"{e.strerror or e}): start it (mlflow server --port {port}) or fix --tracking-uri; "
                                "leave it out to track into EXP/mlflow.db") from None
        elif scheme == "sqlite" or scheme == "file" or scheme == "":
            path = _local_store_path(uri)
            if path is None or not path.parent.is_dir():
                raise MCRLError(f"--tracking-uri {uri}: its directory {path.parent if path else '?'} does not exist: "
                                "create it, or leave --tracking-uri out to track into EXP/mlflow.db")
            return cls(uri, False)  # a local store is created on first use
        try:
            with _no_retries():
                client_cls(tracking_uri=uri).search_experiments(max_results=1)
        except Exception as e:
            raise MCRLError(f"MLflow tracking URI {uri} cannot be used ({_first_line(e)}): fix --tracking-uri "
                            "or the server's credentials (MLFLOW_TRACKING_TOKEN, ...)") from None
        return cls(uri, False)

    def open(self, exp: Path, sweep_id: str, preset: str | None) -> None:
        """Create (or find) this sweep's MLflow experiment."""
        client_cls = _import_mlflow()
        self.client = client = client_cls(tracking_uri=self.uri)
        self.sweep_id = sweep_id
        name = Path(exp).name
        tags = {SWEEP_TAG: sweep_id, "mcrl.experiment_dir": str(Path(exp).absolute()), "mcrl.preset": str(preset)}
        for candidate in (name, f"{name}-{sweep_id[:8]}"):
            found = client.get_experiment_by_name(candidate)
            if found is None:
                kw = {}
                if self.default_store:
                    kw["artifact_location"] = (Path(exp).absolute() / "mlartifacts").as_uri()
                self.experiment_id = client.create_experiment(candidate, tags=tags, **kw)
                self.experiment_name = candidate
                return
            if found.tags.get(SWEEP_TAG) == sweep_id:  # this sweep, logged before
                if found.lifecycle_stage == "deleted":
                    client.restore_experiment(found.experiment_id)
                self.experiment_id, self.experiment_name = found.experiment_id, candidate
                return
        raise MCRLError(f"MLflow experiments {name!r} and {name}-{sweep_id[:8]!r} exist for other sweeps: "
                        "choose another --exp name")

    def _runs_named(self, name: str):
        return self.client.search_runs([self.experiment_id], filter_string=f"tags.`{RUN_TAG}` = '{name}'",
                                       max_results=50)

    def is_logged(self, name: str) -> bool:
        return any(r.info.status == "FINISHED" for r in self._runs_named(name))

    def log_run(self, run: RunPlan, run_dir: Path) -> str:
        """Log one finished mcrl run from its directory; returns the MLflow run id.
        A half-logged earlier attempt (the sweep was killed while logging) is replaced."""
        from mlflow.entities import Metric, Param

        client = self.client
        run_dir = Path(run_dir)
        for old in self._runs_named(run.name):
            if old.info.status == "FINISHED":
                return old.info.run_id
            client.delete_run(old.info.run_id)
        # the config the run was trained with (the plan's, should the run directory have none)
        config = (rundir.read_config(run_dir) if (run_dir / rundir.CONFIG).is_file() else run.config).to_dict()
        tags = {RUN_TAG: run.name, SWEEP_TAG: self.sweep_id or "", "mcrl.config_key": run.config_key,
                "mcrl.seed": str(run.seed), "mcrl.run_dir": str(Path(run_dir).absolute())}
        mlrun = client.create_run(self.experiment_id, run_name=run.name, tags=tags)
        rid = mlrun.info.run_id
        try:
            params = [Param(k, _param_value(v)) for k, v in sorted(config.items())]
            params.append(Param("config_key", run.config_key))
            for i in range(0, len(params), _PARAM_BATCH):
                client.log_batch(rid, params=params[i:i + _PARAM_BATCH])
            ts = int(time.time() * 1000)
            metrics = [Metric(k, v, ts, step) for k, v, step in metric_series(run_dir)]
            for i in range(0, len(metrics), _BATCH):
                client.log_batch(rid, metrics=metrics[i:i + _BATCH])
            for f in (rundir.CONFIG, rundir.METRICS, rundir.EVAL):
                if (run_dir / f).is_file():
                    client.log_artifact(rid, str(run_dir / f))
            for video in sorted((run_dir / rundir.VIDEOS).glob("*.mp4")):  # from `--set video_every=N`
                client.log_artifact(rid, str(video), artifact_path=rundir.VIDEOS)
            with tempfile.TemporaryDirectory(prefix="mcrl-plot-") as tmp:
                try:
                    from mcrl.analysis.plots import plot_run  # matplotlib and scipy: only when logging a run

                    png = plot_run(run_dir, Path(tmp) / "curves.png")
                    client.log_artifact(rid, str(png))
                except MCRLError:
                    pass  # nothing to plot yet
        except BaseException:
            client.set_terminated(rid, "FAILED")
            raise
        client.set_terminated(rid, "FINISHED")
        return rid


def _metric_key(col: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-. /]", "_", col)


EVAL_METRICS = ("success_rate", "mean_return")  # eval.csv's columns, logged as eval/<column>


def _header(path: Path) -> list[str]:
    """The columns a CSV's header names (a reader may add other names for renamed columns: those are not logged)."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [c.strip() for c in next(csv.reader(f), [])]


def metric_series(run_dir: Path) -> list[tuple[str, float, int]]:
    """(MLflow name, value, env step) of a run's metrics, one name per metric: metrics.csv's columns as its header
    names them, except ``eval_*``, which repeat the last evaluation at every log row; the evaluations themselves
    come from eval.csv, at the steps they ran, as ``eval/success_rate`` and ``eval/mean_return``. Empty and
    non-finite cells are left out."""
    out: list[tuple[str, float, int]] = []
    cols = [c for c in _header(run_dir / rundir.METRICS) if c != "step" and not c.startswith("eval_")]
    for source, names in ((rundir.METRICS, {c: _metric_key(c) for c in cols}),
                          (rundir.EVAL, {c: f"eval/{c}" for c in EVAL_METRICS})):
        for row in rundir.read_rows(run_dir / source):
            step = _finite(row.get("step"))
            if step is None:
                continue
            out += [(name, v, int(step)) for col, name in names.items() if (v := _finite(row.get(col))) is not None]
    return out


def _local_store_path(uri: str) -> Path | None:
    if uri.startswith("sqlite:///"):
        return Path(uri[len("sqlite:///"):])
    if uri.startswith("file://"):
        return Path(urlparse(uri).path)
    if "://" not in uri:
        return Path(uri).absolute()
    return None
