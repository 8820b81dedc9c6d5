"""The `mcrl` command line. Every user error ends in one line on stderr and exit code 2; a run stopped by SIGINT or
SIGTERM ends with 130 or 143 after saving a checkpoint it resumes from exactly (`mcrl.run.stop`)."""
from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import sys
from pathlib import Path

from mcrl.errors import MCRLError
from mcrl.progress import progress as progress_bar
from mcrl.run import rundir, stop
from mcrl.extras import PLOT_MODULES, RENDER_MODULES, REPORT_MODULES, require_all, require_installed

DEFAULT_PRESET = "fetchreach-sacmc"


def _overrides(args) -> dict:
    from mcrl.config import parse_set

    ov = parse_set(args.set or [])
    if getattr(args, "env", None):
        ov["env_id"] = args.env
    if getattr(args, "seed", None) is not None:
        ov["seed"] = args.seed
    if getattr(args, "steps", None) is not None:
        ov["total_steps"] = args.steps
    if getattr(args, "out_dir", None):
        ov["out_dir"] = args.out_dir
    if getattr(args, "video_every", None) is not None:
        ov["video_every"] = args.video_every
    return ov


def cmd_train(args) -> int:
    from mcrl.config import resolve_config
    from mcrl.run import trainer
    from mcrl.video.render import record_training_video

    try:
        if args.resume:
            if args.preset or args.env or args.set:
                raise MCRLError("--resume continues a run with its own config.json: drop --preset/--env/--set")
            run_dir = trainer.resume(args.resume, progress=not args.no_progress, total_steps=args.steps,
                                     video=record_training_video)
        else:
            preset = args.preset or (None if args.env else DEFAULT_PRESET)
            cfg = resolve_config(preset, _overrides(args))
            run_dir = trainer.train(cfg, args.run_dir, progress=not args.no_progress, video=record_training_video)
    except stop.Stopped as e:
        ((run_dir, step),) = e.saved
        print(f"mcrl: {e}: saved at step {step:,} ({rundir.checkpoint_root(run_dir)}/"
              f"{rundir.checkpoint_name(step)}); continue exactly with `mcrl train --resume {run_dir}`",
              file=sys.stderr)
        return e.exit_code
    summary = rundir.read_summary(run_dir)
    print(f"run directory: {run_dir}")
    if summary:
        sr = summary.get("success_rate")
        print(f"final evaluation: success rate {'n/a' if sr is None else f'{sr:.2f}'}, "
              f"mean return {summary.get('mean_return'):.2f}")
    print(f"metrics: {run_dir / rundir.METRICS}, {run_dir / rundir.EVAL}; TensorBoard: tensorboard --logdir {run_dir}")
    return 0


def cmd_eval(args) -> int:
    from mcrl.run.evaluation import evaluate_run

    res = evaluate_run(args.run_dir, episodes=args.episodes, checkpoint=args.checkpoint,
                       progress=not args.no_progress)
    sr = res["success_rate"]
    print(f"episodes: {res['episodes']}  success rate: {'n/a' if sr is None else f'{sr:.3f}'}  "
          f"mean return: {res['mean_return']:.3f}")
    return 0


def cmd_presets(args) -> int:
    from mcrl.config import KEY_NOTES, PRESETS, Config, resolve_config
    from mcrl.renames import old_name

    if args.keys:
        for k, v in Config().to_dict().items():
            note = "; ".join(([KEY_NOTES[k]] if k in KEY_NOTES else []) + ([f"was {old_name(k)}"] * (old_name(k) != k)))
            print(f"{k} = {v!r}" + (f"  # {note}" if note else ""))
        return 0
    if args.name:
        print(json.dumps(resolve_config(args.name).to_dict(), indent=2, sort_keys=True))
        return 0
    width = max(map(len, PRESETS))
    for name, (desc, _) in PRESETS.items():
        print(f"{name:<{width}}  {desc}")
    return 0


def cmd_measure(args) -> int:
    import numpy as np

    from mcrl.algo.mc import load_transitions, measure

    s, a, s2 = load_transitions(args.data)
    if args.out and Path(args.out).suffix not in (".npy", ".csv"):
        raise MCRLError(f"--out {args.out}: use a .npy or .csv file name")
    bar = progress_bar(args.max_steps, "fitting MC models", enabled=not args.no_progress)

    def progress(t, loss):
        bar.postfix(f"heldout_nll={loss:.4f}")
        bar.set(t)

    res = measure(s, a, s2, hidden=tuple(args.hidden), lr=args.lr, batch_size=args.batch_size,
                  max_steps=args.max_steps, seed=args.seed, progress=progress if bar else None)
    if bar:
        bar.close()
    n, held, mean_all = len(s), len(res.heldout), float(res.per_transition_kl.mean())  # which set each number is over
    print(f"mean MC (KL per transition): {res.mean_kl:.6f} nats over the {held} held-out transitions (the models were "
          f"fitted on the other {n - held}); over all {n}: {mean_all:.6f} nats  [held-out NLL {res.heldout_nll:.4f} "
          f"at step {res.steps}]")
    if args.out:
        out = Path(args.out)
        tmp = out.with_name(out.name + ".tmp")
        if out.suffix == ".csv":
            np.savetxt(tmp, res.per_transition_kl, header="kl_nats", comments="", fmt="%.8g")
        else:
            with open(tmp, "wb") as f:
                np.save(f, res.per_transition_kl)
        os.replace(tmp, out)
        print(f"per-transition KL of all {n} transitions (mean {mean_all:.6f} nats) written to {out}")
    return 0


def cmd_plot(args) -> int:
    require_all(PLOT_MODULES, None, "mcrl plot")
    from mcrl.analysis.plots import plot_run

    print(f"wrote {plot_run(args.run_dir, args.out)}")
    return 0


def cmd_report(args) -> int:
    require_all(REPORT_MODULES, None, "mcrl report")
    from mcrl.analysis.report import write_report

    if args.readme:  # checked before the report is written: a bad README leaves nothing half done
        from mcrl.decide.report import is_sequential, readme_answer, write_answer

        if not is_sequential(args.experiment_dir):
            raise MCRLError(f"--readme writes a sequential plan's verdict: {args.experiment_dir} has no plan.yaml")
        if not Path(args.readme).is_file():
            raise MCRLError(f"--readme {args.readme}: no such file; give the README that holds the answer block")
        readme_answer(args.readme)  # raises when the markers are missing
    print(f"wrote {write_report(args.experiment_dir, args.out, fmt=args.format, extra_runs=args.with_dirs)}")
    if args.readme:
        changed = write_answer(args.experiment_dir, args.readme)
        print(f"{'updated' if changed else 'unchanged'}: the confirmatory answer in {args.readme}")
    return 0


def cmd_sweep(args) -> int:
    if not args.dry_run:  # a dry run only plans; the sweep may run elsewhere
        # Looked up, not imported: Ray must be imported after `mcrl sweep` sets its auth environment.
        if args.backend == "ray":
            require_installed("ray", "sweep", "mcrl sweep --backend ray")
        if args.tracking or args.tracking_uri:
            require_installed("mlflow", "sweep", "mcrl sweep --tracking")

    from mcrl import sweep
    from mcrl.config import parse_set

    fixed = parse_set(args.set or [])
    if args.steps is not None:
        fixed["total_steps"] = args.steps
    if args.file:
        if args.preset or args.alphas is not None or args.seeds is not None:
            raise MCRLError("--file gives the preset and the grid: drop --preset/--alphas/--seeds "
                            "(or put them in the file)")
        plan = sweep.plan_from_file(args.file, fixed)
    elif (args.exp is not None and not (args.preset or args.alphas or args.seeds or fixed)
          and (args.exp / rundir.SWEEP_JSON).is_file()):
        plan = sweep.plan_from_experiment(args.exp)
    else:
        plan = sweep.plan_from_args(args.preset or DEFAULT_PRESET, args.alphas, args.seeds, fixed)
    if args.dry_run:
        for r in plan.runs:
            print(f"{r.name}  [{r.config_key}, seed {r.seed}]  {r.overrides}")
        print(f"{len(plan.runs)} runs, preset {plan.preset}; nothing written (--dry-run)")
        return 0
    try:
        res = sweep.run_sweep(plan, args.exp, backend=args.backend, workers=args.workers,
                              threads_per_run=args.threads_per_run, tracking=args.tracking,
                              tracking_uri=args.tracking_uri, retries=args.retries,
                              progress=not args.no_progress, command=shlex.join(["mcrl", *args.argv]),
                              **sweep.backend.given_options(args))
    except KeyboardInterrupt:  # a second signal: the runs were killed, each keeps its last checkpoint
        print("mcrl: sweep interrupted; the same command (with --exp) resumes it from the runs' last checkpoints",
              file=sys.stderr)
        return stop.exit_code()
    done = len(res.finished) + len(res.skipped)
    print(f"experiment directory: {res.exp_dir} ({done} of {len(plan.runs)} runs finished)")
    if res.tracking_uri:
        from mcrl.sweep.tracking import ui_command

        print(f"MLflow (experiment {res.tracking_experiment}): {ui_command(res.tracking_uri)}")
    print(f"report: mcrl report {res.exp_dir}")
    if res.failed:
        print(f"mcrl: {len(res.failed)} run(s) failed ({', '.join(res.failed)}): fix the cause and re-run "
              f"`mcrl sweep --exp {res.exp_dir}` to resume them", file=sys.stderr)
    if res.locked:
        print(f"mcrl: {len(res.locked)} run(s) locked by another process ({', '.join(res.locked)}): re-run "
              f"`mcrl sweep --exp {res.exp_dir}` once it has ended", file=sys.stderr)
    if res.stopped_by is not None or res.stopped:
        why = f"stopped by {signal.Signals(res.stopped_by).name}" if res.stopped_by is not None else "stopped"
        print(f"mcrl: sweep {why}: {len(res.stopped)} run(s) saved at their episode's end; "
              f"`mcrl sweep --exp {res.exp_dir}` resumes them exactly", file=sys.stderr)
    if res.stopped_by is not None:
        return 128 + res.stopped_by
    return 1 if res.failed or res.stopped or res.locked else 0


def cmd_decide(args) -> int:
    from mcrl.decide import runner
    from mcrl.decide.plan import load_plan
    from mcrl.sweep.backend import given_options

    plan = load_plan(args.plan)
    if args.dry_run:
        print(runner.dry_run(plan))
        return 0
    if args.look:
        print(runner.summary_line(runner.look(plan, runner.check_commit(plan, args.any_commit))))
        return 0
    options = dict(backend=args.backend, workers=args.workers, threads_per_run=args.threads_per_run,
                   retries=args.retries, progress=not args.no_progress, **given_options(args))
    try:
        st = runner.decide(plan.path, once=args.once, any_commit=args.any_commit, **options)
    except runner.SweepIncomplete as e:
        print(f"mcrl: {e}", file=sys.stderr)
        return 128 + e.result.stopped_by if e.result.stopped_by is not None else 1
    except KeyboardInterrupt:
        print(f"mcrl: interrupted; no look taken; `mcrl decide {plan.path}` resumes the batch", file=sys.stderr)
        return stop.exit_code()
    return 0


def cmd_render(args) -> int:
    require_all(RENDER_MODULES + (("imageio_ffmpeg",) if args.format == "mp4" else ()), None, "mcrl render")
    from mcrl.video.render import render_run

    path = render_run(args.run_dir, episodes=args.episodes, fmt=args.format, checkpoint_step=args.checkpoint,
                      out=args.out, fps=args.fps, progress=not args.no_progress)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from mcrl.sweep import backend as sweep_backends  # the registry only: imports neither jax nor ray

    parser = argparse.ArgumentParser(prog="mcrl", description="SAC-MC: reinforcement learning with morphological "
                                     "computation as an intrinsic reward")
    sub = parser.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train SAC / SAC-MC (default preset: fetchreach-sacmc)")
    t.add_argument("--preset", help="a preset name (`mcrl presets`)")
    t.add_argument("--env", help="any gymnasium id with a Box action space (overrides the preset's env)")
    t.add_argument("--seed", type=int)
    t.add_argument("--steps", type=int, help="total environment steps")
    t.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    t.add_argument("--run-dir", type=Path, help="where to write the run (default: runs/<preset>-<settings that "
                   "differ from it>-s<seed>-<time>, e.g. runs/fetchreach-sac-intrinsic=rnd-a0.2-s0-<time>)")
    t.add_argument("--out-dir", help="parent of the default run directory")
    t.add_argument("--resume", metavar="RUN_DIR", help="continue a killed run from its newest checkpoint")
    t.add_argument("--video-every", type=int, help="record an evaluation video every N steps")
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="re-evaluate a saved policy (deterministic actions)")
    e.add_argument("run_dir")
    e.add_argument("--episodes", type=int)
    e.add_argument("--checkpoint", type=int, metavar="STEP")
    e.add_argument("--no-progress", action="store_true")
    e.set_defaults(func=cmd_eval)

    ps = sub.add_parser("presets", help="list presets; `mcrl presets NAME` shows one resolved")
    ps.add_argument("name", nargs="?")
    ps.add_argument("--keys", action="store_true", help="list every config key with its default")
    ps.set_defaults(func=cmd_presets)

    m = sub.add_parser("measure", help="MC of logged transitions: fit both models, print the mean KL")
    m.add_argument("data", help=".npz with arrays states, actions, next_states")
    m.add_argument("--out", help="write per-transition KL (nats) to this .npy or .csv")
    m.add_argument("--max-steps", type=int, default=20_000)
    m.add_argument("--batch-size", type=int, default=256)
    m.add_argument("--lr", type=float, default=1e-3)
    m.add_argument("--hidden", type=int, nargs="+", default=[256] * 5)
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--no-progress", action="store_true")
    m.set_defaults(func=cmd_measure)

    p = sub.add_parser("plot", help="learning curves of one run (PNG)")
    p.add_argument("run_dir")
    p.add_argument("--out", help="PNG path (default RUN_DIR/curves.png)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("report", help="statistical report of a sweep (Markdown + PNG, or HTML)")
    p.add_argument("experiment_dir")
    p.add_argument("--format", choices=("md", "html"), default="md")
    p.add_argument("--out", help="output directory (default EXPERIMENT_DIR/report)")
    p.add_argument("--with", dest="with_dirs", action="append", metavar="DIR[=LABEL]", default=[],
                   help="more runs to include (repeatable): another experiment directory, a run directory, or a "
                   "directory of run directories (directly or in its runs/), e.g. reference arms with a peer.json; "
                   "=LABEL names its arm in the report (e.g. --with experiments/variant='SAC-MC, code variant')")
    p.add_argument("--readme", help="a sequential plan's directory: also write its verdict between the "
                   "<!-- confirmatory:start --> and <!-- confirmatory:end --> markers of this file (e.g. README.md)")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("sweep", help="many runs (alphas x seeds, or a grid file) into one experiment directory",
                       description="Run a grid of configurations and seeds into one experiment directory "
                       "(EXP/sweep.json + EXP/runs/<name>/). Re-running with the same --exp skips finished runs "
                       "and resumes the others from their checkpoints; `mcrl sweep --exp EXP` alone continues "
                       "the sweep recorded there.")
    p.add_argument("--preset", help="a preset name (`mcrl presets`)")
    p.add_argument("--alphas", help="comma-separated intrinsic_alpha values, e.g. 0,0.2,0.4,0.6,0.8,1.0")
    p.add_argument("--seeds", help="a count (6 = seeds 0..5) or a comma-separated list of seeds")
    p.add_argument("--steps", type=int, help="total environment steps of every run")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="fixed override of a config key (repeatable)")
    p.add_argument("--file", help="YAML sweep file: preset, grid: {key: [values]}, optional set: {key: value}, seeds")
    p.add_argument("--exp", type=Path, help="experiment directory (default experiments/<preset>-<time>)")
    p.add_argument("--backend", choices=sweep_backends.names(), default="local",
                   help="local: a process per run; ray: a Ray task per run; vmap: runs that share shapes train as "
                   "one vmapped computation (one process per group, all cores; the fastest on a GPU)")
    p.add_argument("--group-size", type=int, help="vmap: at most N runs per group (default: all that fit together)")
    p.add_argument("--env-workers", type=int, default=0, help="vmap: step the group's environments in N processes "
                   "(default 0: in the group's process)")
    p.add_argument("--workers", type=int, help="runs at a time (default: the number of cores; ray with --address: "
                   "as many as the cluster's CPUs allow)")
    p.add_argument("--threads-per-run", type=int, help="pin each run's process to N cores (default: not pinned, "
                   "every core as `mcrl train`; the cores also set XLA's float results, docs/algorithm.md)")
    p.add_argument("--address", help="Ray cluster address (HOST:PORT, ray://HOST:PORT or auto); default: a local "
                   "Ray instance")
    p.add_argument("--gpus-per-run", type=float, default=0.0, help="GPUs each Ray task asks for (ray only)")
    p.add_argument("--retries", type=int, default=0, help="restart a run whose worker died, from its last "
                   "checkpoint, up to N times")
    p.add_argument("--tracking", action="store_true", help="log every run to MLflow (default store: EXP/mlflow.db)")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (implies --tracking), e.g. http://host:5000")
    p.add_argument("--dry-run", action="store_true", help="validate and list the runs; write nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (run lines are still printed)")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("decide", help="run a sequential plan (plan.yaml) batch by batch until its claims are decided",
                       description="Run the next batch of a preregistered sequential plan through a sweep backend, "
                       "then take the look (group-sequential bounds) and append it to looks.jsonl beside the plan; "
                       "repeat until every claim is decided. Stopping and running it again resumes the batch.")
    p.add_argument("plan", help="the plan.yaml (or its directory); runs go into runs/ beside it")
    p.add_argument("--dry-run", action="store_true", help="print the boundary table and the next batch's runs")
    p.add_argument("--once", action="store_true", help="one batch and its look, then stop")
    p.add_argument("--look", action="store_true", help="take the next look now from finished runs (starts no run)")
    p.add_argument("--any-commit", action="store_true", help="run even if this mcrl is not the plan's commit")
    p.add_argument("--backend", choices=sweep_backends.names(), default="local")
    p.add_argument("--workers", type=int, help="runs at a time (default: the number of cores)")
    p.add_argument("--threads-per-run", type=int, help="pin each run's process to N cores")
    p.add_argument("--address", help="Ray cluster address (ray only)")
    p.add_argument("--group-size", type=int, help="vmap: at most N runs per group")
    p.add_argument("--env-workers", type=int, default=0, help="vmap: environment processes per group")
    p.add_argument("--retries", type=int, default=0, help="restart a run whose worker died, up to N times")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_decide)

    p = sub.add_parser("render", help="video of the saved policy with its intrinsic reward's timeline")
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--format", choices=("mp4", "gif"), default="mp4")
    p.add_argument("--checkpoint", type=int, metavar="STEP", help="a checkpoint's step (default: the newest)")
    p.add_argument("--out", help="video path (default RUN_DIR/videos/policy_step<STEP>.<format>)")
    p.add_argument("--fps", type=float, default=25.0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)  # as typed, for EXP/provenance.json
    try:
        return args.func(args)
    except MCRLError as e:
        print(f"mcrl: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a second Ctrl-C, or one outside training: nothing saved beyond the last checkpoint
        print("mcrl: interrupted; a run continues from its last checkpoint with `mcrl train --resume RUN_DIR`",
              file=sys.stderr)
        return stop.exit_code()


if __name__ == "__main__":
    sys.exit(main())
