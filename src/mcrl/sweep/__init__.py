"""``mcrl sweep``: many runs of one experiment (a grid over config keys and seeds) in one directory.

An experiment directory ``EXP`` holds ``sweep.json`` (the runs: name, config_key, seed, overrides;
the format ``mcrl report`` reads) and one run directory per run, ``EXP/runs/<name>/`` (see
docs/run-directory.md). Running the same sweep again on the same ``EXP`` skips finished runs
(``done`` exists) and resumes unfinished ones from their newest checkpoint, so killing the sweep or
one of its workers loses at most each run's work since its last checkpoint. Everything is validated
(sweep file, every grid point with ``resolve_config``, environments, the Ray address, the tracking
URI) before ``EXP`` is created: a bad sweep writes nothing.

Python API::

    from mcrl import sweep
    plan = sweep.plan_from_args("fetchreach-sacmc", alphas="0,0.2", seeds=3)   # or plan_from_file / _experiment
    result = sweep.run_sweep(plan, "experiments/alpha", backend="local", workers=2)

The package, one idea per module (each imports only those above it; none imports jax or ray at import
time, since a local worker must pin its cores before jax is imported):

- ``plan``: grid / arguments / YAML file / ``sweep.json`` -> a ``SweepPlan``, a list of ``RunPlan``.
- ``files``: a run directory seen from the driver: its state, and its files shipped between worker
  and driver (file names and formats are ``mcrl.run.rundir``'s).
- ``worker``: inside a worker process: its cores (``pin_cores``) and thread limits (``thread_env``), training
  its runs, dying with the driver.
- ``backend``: the interface every backend implements (launch, poll, request stop) and their registry
  (``--backend``).
- ``driver``: the one driver loop (queue, retries, stop forwarding, locked runs, progress), its output and the
  ``SweepResult``.
- ``local``: the local backend, one spawned process per run; and the vmap backend, one spawned process per
  group of runs trained as one vmapped computation (``mcrl.run.group``).
- ``ray_backend``: the Ray backend, one Ray task per run, shipping files back when the worker cannot
  see ``EXP``.
- ``tracking``: MLflow logging of finished runs (imported only with ``--tracking``).
- ``provenance``: ``EXP/provenance.json``, one entry per sweep call: command, mcrl version and commit, machine,
  start and end.
- ``experiment``: ``run_sweep``: validate, lock ``EXP``, write ``sweep.json``, hand runs to a backend.
"""
from mcrl.sweep.driver import SweepResult
from mcrl.sweep.experiment import default_exp_dir, run_sweep
from mcrl.sweep.plan import (RunPlan, SweepPlan, build_plan, parse_alphas, parse_seeds, plan_from_args,
                             plan_from_experiment, plan_from_file)

__all__ = ["RunPlan", "SweepPlan", "SweepResult", "build_plan", "default_exp_dir", "parse_alphas", "parse_seeds",
           "plan_from_args", "plan_from_experiment", "plan_from_file", "run_sweep"]
