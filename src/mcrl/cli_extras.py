"""Subcommands beyond training: plot, report, render, sweep.

Each checks the packages it needs first (:mod:`mcrl.extras`): a missing one is a one-line error
naming the install command, before anything is written.
"""
from __future__ import annotations

from pathlib import Path

from mcrl.cli import _EXTRA_COMMANDS
from mcrl.extras import PLOT_MODULES, RENDER_MODULES, REPORT_MODULES, require_all, require_installed


def _plot(sub) -> None:
    p = sub.add_parser("plot", help="learning curves of one run (PNG)")
    p.add_argument("run_dir")
    p.add_argument("--out", help="PNG path (default RUN_DIR/curves.png)")

    def run(args) -> int:
        require_all(PLOT_MODULES, None, "mcrl plot")
        from mcrl.plots import plot_run

        print(f"wrote {plot_run(args.run_dir, args.out)}")
        return 0

    p.set_defaults(func=run)


def _report(sub) -> None:
    p = sub.add_parser("report", help="statistical report of a sweep (Markdown + PNG, or HTML)")
    p.add_argument("experiment_dir")
    p.add_argument("--format", choices=("md", "html"), default="md")
    p.add_argument("--out", help="output directory (default EXPERIMENT_DIR/report)")
    p.add_argument("--with", dest="with_dirs", action="append", metavar="DIR", default=[],
                   help="more runs to include (repeatable): another experiment directory, a run directory, or a "
                   "directory of run directories, e.g. reference arms with a peer.json")

    def run(args) -> int:
        require_all(REPORT_MODULES, None, "mcrl report")
        from mcrl.report import write_report

        print(f"wrote {write_report(args.experiment_dir, args.out, fmt=args.format, extra_runs=args.with_dirs)}")
        return 0

    p.set_defaults(func=run)


def _sweep(sub) -> None:
    p = sub.add_parser("sweep", help="many runs (alphas x seeds, or a grid file) into one experiment directory",
                       description="Run a grid of configurations and seeds into one experiment directory "
                       "(EXP/sweep.json + EXP/runs/<name>/). Re-running with the same --exp skips finished runs "
                       "and resumes the others from their checkpoints; `mcrl sweep --exp EXP` alone continues "
                       "the sweep recorded there.")
    p.add_argument("--preset", help="a preset name (`mcrl presets`)")
    p.add_argument("--alphas", help="comma-separated mc_alpha values, e.g. 0,0.2,0.4,0.6,0.8,1.0")
    p.add_argument("--seeds", help="a count (6 = seeds 0..5) or a comma-separated list of seeds")
    p.add_argument("--steps", type=int, help="total environment steps of every run")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="fixed override of a config key (repeatable)")
    p.add_argument("--file", help="YAML sweep file: preset, grid: {key: [values]}, optional set: {key: value}, seeds")
    p.add_argument("--exp", type=Path, help="experiment directory (default experiments/<preset>-<time>)")
    p.add_argument("--backend", choices=("local", "ray"), default="local")
    p.add_argument("--workers", type=int, help="runs at a time (default: the number of cores; ray with --address: "
                   "as many as the cluster's CPUs allow)")
    p.add_argument("--threads-per-run", type=int, help="threads of each run (default: cores // workers)")
    p.add_argument("--address", help="Ray cluster address (HOST:PORT, ray://HOST:PORT or auto); default: a local "
                   "Ray instance")
    p.add_argument("--gpus-per-run", type=float, default=0.0, help="GPUs each Ray task asks for (ray only)")
    p.add_argument("--retries", type=int, default=0, help="restart a run whose worker died, from its last "
                   "checkpoint, up to N times")
    p.add_argument("--tracking", action="store_true", help="log every run to MLflow (default store: EXP/mlflow.db)")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (implies --tracking), e.g. http://host:5000")
    p.add_argument("--dry-run", action="store_true", help="validate and list the runs; write nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (run lines are still printed)")

    def run(args) -> int:
        import sys

        if not args.dry_run:  # a dry run only plans; the sweep may run elsewhere
            # Looked up, not imported: Ray must be imported after `mcrl sweep` sets its auth environment.
            if args.backend == "ray":
                require_installed("ray", "sweep", "mcrl sweep --backend ray")
            if args.tracking or args.tracking_uri:
                require_installed("mlflow", "sweep", "mcrl sweep --tracking")

        from mcrl.cli import DEFAULT_PRESET
        from mcrl.config import parse_set
        from mcrl.errors import MCRLError
        from mcrl import sweep

        fixed = parse_set(args.set or [])
        if args.steps is not None:
            fixed["total_steps"] = args.steps
        if args.file:
            if args.preset or args.alphas is not None or args.seeds is not None:
                raise MCRLError("--file gives the preset and the grid: drop --preset/--alphas/--seeds "
                                "(or put them in the file)")
            plan = sweep.plan_from_file(args.file, fixed)
        elif (args.exp is not None and not (args.preset or args.alphas or args.seeds or fixed)
              and (args.exp / "sweep.json").is_file()):
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
                                  threads_per_run=args.threads_per_run, address=args.address,
                                  gpus_per_run=args.gpus_per_run, tracking=args.tracking,
                                  tracking_uri=args.tracking_uri, retries=args.retries,
                                  progress=not args.no_progress)
        except KeyboardInterrupt:
            print("mcrl: sweep interrupted; the same command (with --exp) resumes it from the runs' checkpoints",
                  file=sys.stderr)
            return 130
        done = len(res.finished) + len(res.skipped)
        print(f"experiment directory: {res.exp_dir} ({done} of {len(plan.runs)} runs finished)")
        if res.tracking_uri:
            from mcrl.tracking import ui_command

            print(f"MLflow (experiment {res.tracking_experiment}): {ui_command(res.tracking_uri)}")
        print(f"report: mcrl report {res.exp_dir}")
        if res.failed:
            print(f"mcrl: {len(res.failed)} run(s) failed ({', '.join(res.failed)}): fix the cause and re-run "
                  f"`mcrl sweep --exp {res.exp_dir}` to resume them", file=sys.stderr)
            return 1
        return 0

    p.set_defaults(func=run)


_EXTRA_COMMANDS.extend([_plot, _report, _sweep])


def _render(sub) -> None:
    p = sub.add_parser("render", help="video of the saved policy with the MC reward timeline")
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--format", choices=("mp4", "gif"), default="mp4")
    p.add_argument("--checkpoint", type=int, metavar="STEP", help="a checkpoint's step (default: the newest)")
    p.add_argument("--out", help="video path (default RUN_DIR/videos/policy_step<STEP>.<format>)")
    p.add_argument("--fps", type=float, default=25.0)

    def run(args) -> int:
        require_all(RENDER_MODULES + (("imageio_ffmpeg",) if args.format == "mp4" else ()), None, "mcrl render")
        from mcrl.render import render_run

        path = render_run(args.run_dir, episodes=args.episodes, fmt=args.format, checkpoint_step=args.checkpoint,
                          out=args.out, fps=args.fps)
        print(f"wrote {path}")
        return 0

    p.set_defaults(func=run)


_EXTRA_COMMANDS.append(_render)
