"""Learning-dynamics parity: mcrl's SAC+HER against stable-baselines3's at identical settings.

Two subcommands (run from the repository root; the ``sb3`` one needs ``pip install -e ".[bench]"``)::

    python studies/sb3-parity/parity_sb3.py sb3 --seed N [--steps 150000] [--preset fetchpush-sac]
                                                [--set key=value ...] [--threads 1] --run-dir DIR [--overwrite]
    python studies/sb3-parity/parity_sb3.py sb3 --resume --run-dir DIR
    python studies/sb3-parity/parity_sb3.py compare --mcrl RUN_DIR... --sb3 RUN_DIR... --out DIR [--every 5000]

``sb3`` trains stable-baselines3's SAC with ``HerReplayBuffer`` at exactly the settings of an mcrl preset
(read from ``mcrl.config.resolve_config``) and writes an mcrl-format run directory (``config.json``,
``metrics.csv``, ``eval.csv``, ``final_eval.json``, ``done``, plus ``peer.json`` naming the system and
``sb3_model.zip``), so the same tools read both. Options SB3 cannot mirror fail with a message. It writes
checkpoints every ``checkpoint_every`` steps; ``--resume`` continues a killed run exactly where its last
checkpoint left it.

``compare`` reads run directories of both systems (partial runs too) and writes ``DIR/parity.md`` (tables
every ``--every`` steps of mean Q, entropy coefficient, critic loss and evaluation success per system and
seed, and a per-system summary) and ``DIR/parity.png`` (2x2 panels).

``check`` (a self-test) trains stock SB3 SAC and this script's SAC subclass side by side for a few hundred
steps and confirms their parameters are bit-identical, i.e. that recording the diagnostics changes nothing.
``check-resume`` (a self-test) kills an SB3 run with SIGKILL after a checkpoint, resumes it, and confirms
that it ends bit-identical to the same run uninterrupted.

See docs/studies/sb3-parity.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from _common import md_head, md_row

#: Steps of the per-system summary.
SUMMARY_STEPS = (15_000, 25_000, 45_000)
SYSTEM_COLOURS = {"mcrl": "tab:blue", "sb3": "tab:orange"}


def _die(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


# ------------------------------------------------------------------------------------------ sb3


def cmd_sb3(args: argparse.Namespace) -> int:
    # Before torch (and numpy's BLAS) load: one OpenMP thread per process unless the caller said otherwise.
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    from mcrl.config import Config, parse_set, resolve_config
    from mcrl.errors import MCRLError

    if args.threads < 1:
        return _die(f"--threads {args.threads}: give at least 1")
    if args.resume and args.overwrite:
        return _die("--resume continues the run in --run-dir and --overwrite replaces it: give one of them")
    try:
        if args.resume:  # the run's own config: nothing may change it
            given = [f"--{k}" for k in ("seed", "steps", "preset", "set") if getattr(args, k) is not None]
            if given:
                return _die(f"--resume continues {args.run_dir} with its config.json: drop {', '.join(given)}")
            path = args.run_dir / "config.json"
            if not path.is_file():
                return _die(f"{args.run_dir} holds no run to resume (no config.json): start it without --resume")
            cfg = Config.from_run_json(json.loads(path.read_text()))
        else:
            if args.seed is None:
                return _die("give --seed N (or --resume to continue a run)")
            overrides = parse_set(args.set or [])
            for key in ("seed", "total_steps"):
                if key in overrides:
                    return _die(f"give {key} with --{'seed' if key == 'seed' else 'steps'}, not --set {key}=...")
            overrides["seed"] = args.seed
            if args.steps is not None:
                overrides["total_steps"] = args.steps
            cfg = resolve_config(args.preset or "fetchpush-sac", overrides)
    except (MCRLError, ValueError) as e:
        return _die(str(e))
    try:
        import _sb3
    except ImportError as e:  # pragma: no cover
        return _die(f"cannot import studies/sb3-parity/_sb3.py ({e})")
    try:
        import stable_baselines3  # noqa: F401
        import torch  # noqa: F401
    except ImportError as e:
        return _die(f"{e.name} is not installed: pip install -e \".[bench]\" (torch and stable-baselines3)")
    try:
        run_dir = _sb3.train(cfg, args.run_dir, threads=args.threads, progress=not args.no_progress,
                             overwrite=args.overwrite, resume=args.resume)
    except (_sb3.UnsupportedConfig, FileExistsError, FileNotFoundError, MCRLError) as e:
        return _die(f"cannot mirror this config in stable-baselines3: {e}" if isinstance(e, _sb3.UnsupportedConfig)
                    else str(e))
    done = json.loads((Path(run_dir) / "done").read_text())
    print(f"{run_dir}: step {done['step']}, final success {done.get('success_rate')}, "
          f"mean return {done.get('mean_return')}")
    return 0


def cmd_check_resume(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import tempfile

    import _sb3

    with tempfile.TemporaryDirectory(prefix="mcrl-sb3-resume-") as tmp:
        res = _sb3.check_resume_equivalence(Path(tmp), steps=args.steps, kill_after=args.kill_after, seed=args.seed)
    print(json.dumps(res))
    return 0 if res["identical"] else 1


def cmd_check(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import _sb3

    res = _sb3.check_train_equivalence(steps=args.steps, seed=args.seed)
    print(json.dumps(res))
    return 0 if res["identical"] else 1


# -------------------------------------------------------------------------------------- compare


class RunData:
    """What compare needs from one run directory (mcrl's or an SB3 parity run)."""

    def __init__(self, system: str, run_dir: Path):
        from mcrl.run.rundir import read_json, read_rows

        self.system, self.dir = system, Path(run_dir)
        if not (self.dir / "metrics.csv").is_file():
            raise FileNotFoundError(f"{self.dir} has no metrics.csv: give run directories of `mcrl train` or "
                                    "`parity_sb3.py sb3`")
        self.config = read_json(self.dir / "config.json")
        self.peer = read_json(self.dir / "peer.json")
        self.final = read_json(self.dir / "final_eval.json") or None
        self.finished = (self.dir / "done").exists()
        self.seed = self.config.get("seed")
        metrics = read_rows(self.dir / "metrics.csv")
        evals = read_rows(self.dir / "eval.csv")
        self.metrics = {int(r["step"]): r for r in metrics if r.get("step") is not None}
        # At the last step a run also has its final evaluation (more episodes); both are at that step, keep
        # the last row, which is the final one.
        self.evals = {int(r["step"]): r for r in evals if r.get("step") is not None}

    @property
    def label(self) -> str:
        return f"s{self.seed}" if self.seed is not None else self.dir.name

    @property
    def last_step(self) -> int:
        return max(list(self.metrics) + list(self.evals), default=0)

    def value(self, col: str, step: int) -> float | None:
        """metrics.csv's ``col`` at exactly ``step`` (eval success from eval.csv), None when absent."""
        if col == "eval_success":
            row = self.evals.get(step)
            v = row.get("success_rate") if row else None
        else:
            row = self.metrics.get(step)
            v = row.get(col) if row else None
        return v if v is not None and math.isfinite(v) else None

    def series(self, col: str) -> tuple[list[int], list[float]]:
        src = self.evals if col == "eval_success" else self.metrics
        key = "success_rate" if col == "eval_success" else col
        pts = [(s, r.get(key)) for s, r in sorted(src.items())]
        pts = [(s, v) for s, v in pts if v is not None and math.isfinite(v)]
        return [s for s, _ in pts], [v for _, v in pts]


def _system_name(system: str, runs: list[RunData]) -> str:
    if system == "sb3":
        v = next((r.peer.get("version") for r in runs if r.peer.get("version")), None)
        return f"stable-baselines3 {v}" if v else "stable-baselines3"
    return "mcrl"


def _mean(vals: list[float | None]) -> tuple[float | None, int]:
    xs = [v for v in vals if v is not None]
    return (sum(xs) / len(xs) if xs else None), len(xs)


def _fmt(x: float | None, col: str) -> str:
    if x is None:
        return "—"
    if col == "eval_success":
        return f"{x:.2f}"
    if col == "q_mean":
        return f"{x:.2f}"
    return f"{x:.3g}" if abs(x) >= 1e-3 else f"{x:.2e}"


def _tables(systems: dict[str, list[RunData]], every: int) -> list[str]:
    last = max((r.last_step for runs in systems.values() for r in runs), default=0)
    steps = list(range(every, last + 1, every))
    # The last step of each finished run, when it is not a multiple of --every (e.g. a 3,000-step trial).
    steps = sorted(set(steps) | {r.last_step for runs in systems.values() for r in runs if r.finished})
    lines: list[str] = []
    cols = [("q_mean", "Mean Q (mean over both critics of Q(s, a) on the replay batches of the log interval)"),
            ("ent_coef", "Entropy coefficient (mean over the log interval)"),
            ("critic_loss", "Critic loss (mean over the log interval)"),
            ("eval_success", "Evaluation success rate (eval.csv at that step; at a run's last step: the final "
                             "evaluation)")]
    for col, title in cols:
        head = ["step"]
        for sysname, runs in systems.items():
            head += [f"{_system_name(sysname, runs)} {r.label}" for r in runs] + [f"{_system_name(sysname, runs)} mean"]
        lines += [f"### {title}", "", *md_head(head, "---:")]
        for step in steps:
            cells = [f"{step:,}"]
            any_value = False
            for runs in systems.values():
                vals = [r.value(col, step) for r in runs]
                any_value |= any(v is not None for v in vals)
                m, n = _mean(vals)
                cells += [_fmt(v, col) for v in vals]
                cells.append(_fmt(m, col) + (f" (n={n})" if m is not None and n < len(runs) else ""))
            if any_value:
                lines.append(md_row(cells))
        lines.append("")
    return lines


def _summary(systems: dict[str, list[RunData]]) -> list[str]:
    head = ["system", "step", "runs with data", "mean Q", "entropy coef.", "critic loss", "eval success"]
    lines = md_head(head)
    for sysname, runs in systems.items():
        name = _system_name(sysname, runs)
        for step in SUMMARY_STEPS:
            row = [name, f"{step:,}"]
            ns = []
            vals = []
            for col in ("q_mean", "ent_coef", "critic_loss", "eval_success"):
                m, n = _mean([r.value(col, step) for r in runs])
                vals.append(_fmt(m, col))
                ns.append(n)
            row.append(f"{max(ns)} of {len(runs)}")
            lines.append(md_row(row + vals))
        finals = [r.final for r in runs if r.final and r.final.get("success_rate") is not None]
        if finals:
            m, n = _mean([float(f["success_rate"]) for f in finals])
            per = ", ".join(f"{r.label}: {r.final['success_rate']:.2f} @ {int(r.final['step']):,}"
                            for r in runs if r.final and r.final.get("success_rate") is not None)
            eps = sorted({int(f.get("episodes", 0)) for f in finals})
            lines.append(f"| {name} | final ({'/'.join(map(str, eps))} episodes) | {n} of {len(runs)} | | | | "
                         f"{m:.2f} ({per}) |")
        else:
            lines.append(f"| {name} | final | 0 of {len(runs)} | | | | — (no final_eval.json yet) |")
    return lines


def _runs_list(systems: dict[str, list[RunData]]) -> list[str]:
    head = ["system", "seed", "run directory", "last step", "finished", "steps/s (last row)", "torch threads"]
    lines = md_head(head)
    for sysname, runs in systems.items():
        for r in runs:
            last = r.metrics.get(max(r.metrics)) if r.metrics else None
            sps = last.get("steps_per_s") if last else None
            lines.append(md_row([
                _system_name(sysname, runs), str(r.seed), f"`{r.dir}`", f"{r.last_step:,}",
                "yes" if r.finished else "no", f"{sps:.1f}" if sps else "—",
                str(r.peer.get("torch_threads", "—")) if sysname == "sb3" else "—"]))
    return lines


def _resolved(config: dict) -> dict:
    """A run's config.json as mcrl reads it: keys added after the run was written get the value the run ran
    with (today's default, or the legacy one `Config.from_run_json` supplies), so they are no difference."""
    import dataclasses

    from mcrl.config import Config
    from mcrl.errors import MCRLError

    try:
        return dataclasses.asdict(Config.from_run_json(config))
    except (MCRLError, TypeError, ValueError):
        return config


def _settings_note(systems: dict[str, list[RunData]]) -> list[str]:
    """Flag differing settings between the runs (other than seed, steps and output paths)."""
    ignore = {"seed", "total_steps", "out_dir", "final_eval_episodes", "checkpoint_every", "keep_checkpoints",
              "save_buffer", "video_every", "eval_every", "log_every"}
    configs = [(f"{s} {r.label}", r.config) for s, runs in systems.items() for r in runs if r.config]
    if not configs:
        return ["No config.json found in the runs."]
    configs = [(name, _resolved(c)) for name, c in configs]
    keys = sorted(set().union(*(c for _, c in configs)) - ignore)
    differ = [k for k in keys if len({json.dumps(c.get(k), sort_keys=True) for _, c in configs}) > 1]
    if not differ:
        ref = configs[0][1]
        return [f"All runs share their settings (preset `{ref.get('preset')}`, env `{ref.get('env_id')}`; "
                "seeds, step budgets and logging cadence aside)."]
    return ["**Settings differ between runs** in: " + ", ".join(f"`{k}`" for k in differ)
            + ": the comparison is not like for like."]


def write_plot(systems: dict[str, list[RunData]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    import numpy as np

    panels = [("q_mean", "mean Q", False), ("ent_coef", "entropy coefficient", True),
              ("critic_loss", "critic loss", True), ("eval_success", "eval success rate", False)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True)
    for ax, (col, title, log) in zip(axes.flat, panels):
        for sysname, runs in systems.items():
            colour = SYSTEM_COLOURS.get(sysname, None)
            per_step: dict[int, list[float]] = {}
            for r in runs:
                xs, ys = r.series(col)
                if not xs:
                    continue
                ax.plot(np.array(xs) / 1e3, ys, color=colour, lw=0.8, alpha=0.45)
                for x, y in zip(xs, ys):
                    per_step.setdefault(x, []).append(y)
            if per_step:
                xs = sorted(per_step)
                ax.plot(np.array(xs) / 1e3, [np.mean(per_step[x]) for x in xs], color=colour, lw=2.4,
                        label=f"{_system_name(sysname, runs)} (mean of {len(runs)})")
        if col == "q_mean" and max((abs(y) for ln in ax.get_lines() for y in ln.get_ydata()), default=0) > 100:
            # a diverged critic (thousands) would flatten the settled ones (about -20..+20) into one line
            ax.set_yscale("symlog", linthresh=20)
            lo, hi = ax.get_ylim()
            ax.set_yticks([t for t in (-1000, -100, -20, -10, 0, 10, 20, 100, 1000, 10000) if lo <= t <= hi])
            ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda y, _: f"{y:g}"))
            title += " (linear within ±20, log beyond)"
        ax.set_title(title)
        if log:
            ax.set_yscale("log")
            # Plain numbers (0.5, not 5x10^-1); minor ticks labelled only when the axis spans < 1 decade.
            plain = matplotlib.ticker.FuncFormatter(lambda y, _: f"{y:g}")
            lo, hi = ax.get_ylim()
            ax.yaxis.set_major_formatter(plain)
            ax.yaxis.set_minor_formatter(plain if hi / lo < 10 else matplotlib.ticker.NullFormatter())
        if col == "eval_success":
            ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3, which="both" if log else "major")
    for ax in axes[1]:
        ax.set_xlabel("environment steps (thousands)")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    for ax in axes.flat[1:]:
        h, l = ax.get_legend_handles_labels()
        for hh, ll in zip(h, l):
            if ll not in labels:
                handles.append(hh)
                labels.append(ll)
    fig.legend(handles, labels, loc="upper center", ncol=max(1, len(labels)), frameon=False)
    fig.suptitle("thin: one seed; thick: mean over the seeds that reached the step", y=0.935, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _peaks(systems: dict[str, list[RunData]], after: int) -> list[str]:
    """Per run: the largest mean Q, entropy coefficient and critic loss logged after step ``after`` (past the
    entropy-inflated start, where every critic rises and falls), each with its step, and the last values."""
    head = ["system", "seed", "last step", f"peak mean Q after {after:,} (step)", "peak entropy coef. (step)",
            "peak critic loss (step)", "last mean Q / entropy coef. / critic loss"]
    lines = md_head(head)
    for sysname, runs in systems.items():
        for r in runs:
            cells = [_system_name(sysname, runs), r.label, f"{r.last_step:,}"]
            for col in ("q_mean", "ent_coef", "critic_loss"):
                pts = [(v, s) for s, v in zip(*r.series(col)) if s > after]
                v, s = max(pts) if pts else (None, None)
                cells.append(f"{_fmt(v, col)} ({s:,})" if v is not None else "—")
            steps, _ = r.series("q_mean")
            cells.append(" / ".join(_fmt(r.value(c, steps[-1]), c) for c in ("q_mean", "ent_coef", "critic_loss"))
                         if steps else "—")
            lines.append(md_row(cells))
    return lines


def cmd_compare(args: argparse.Namespace) -> int:
    if args.every < 1:
        return _die(f"--every {args.every}: give a positive number of steps")
    systems: dict[str, list[RunData]] = {}
    try:
        for sysname, dirs in (("mcrl", args.mcrl), ("sb3", args.sb3)):
            runs = [RunData(sysname, Path(d)) for d in dirs or []]
            if runs:
                systems[sysname] = sorted(runs, key=lambda r: (r.seed is None, r.seed or 0, str(r.dir)))
    except FileNotFoundError as e:
        return _die(str(e))
    if not systems:
        return _die("give run directories with --mcrl and/or --sb3")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_plot(systems, out / "parity.png")
    lines = ["# mcrl vs stable-baselines3: learning dynamics at identical settings", "",
             "Made by `python studies/sb3-parity/parity_sb3.py compare` (see docs/studies/sb3-parity.md). "
             "Values are read from each run's `metrics.csv` row at the step (means over that log interval's "
             "gradient steps) and `eval.csv`; "
             "a run that has not reached a step has no value there (—), and the mean is over the runs that have "
             "one (n= says how many when not all).", "",
             *_settings_note(systems), "", "![parity](parity.png)", "", "## Runs", "", *_runs_list(systems), "",
             "## Summary (means over seeds)", "", *_summary(systems), "",
             "## Peaks per run", "", "Whether a critic settles or drifts upward, run by run (a mean that averages "
             "a diverged seed with settled ones hides both).", "", *_peaks(systems, args.settle_after), "",
             f"## Every {args.every:,} steps", "", *_tables(systems, args.every)]
    (out / "parity.md").write_text("\n".join(lines).rstrip() + "\n")
    print(f"wrote {out / 'parity.md'} and {out / 'parity.png'}")
    return 0


# ------------------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("sb3", help="train stable-baselines3 SAC+HER at an mcrl preset's settings")
    s.add_argument("--seed", type=int, help="the run's seed (required unless --resume)")
    s.add_argument("--steps", type=int, help="total environment steps (default: the preset's, 150,000)")
    s.add_argument("--preset", help="mcrl preset (default fetchpush-sac)")
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    s.add_argument("--run-dir", type=Path, required=True, help="run directory to create (or to resume)")
    s.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads (default 1; also OMP_NUM_THREADS unless set)")
    s.add_argument("--overwrite", action="store_true", help="replace the run in --run-dir")
    s.add_argument("--resume", action="store_true",
                   help="continue the run in --run-dir from its newest checkpoint (sb3_checkpoints/)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_sb3)

    c = sub.add_parser("compare", help="tables and plots of mcrl and SB3 run directories")
    c.add_argument("--mcrl", nargs="+", metavar="RUN_DIR", help="mcrl run directories")
    c.add_argument("--sb3", nargs="+", metavar="RUN_DIR", help="run directories of `parity_sb3.py sb3`")
    c.add_argument("--out", type=Path, required=True, help="output directory (parity.md, parity.png)")
    c.add_argument("--every", type=int, default=5000, help="table rows every N steps (default 5000)")
    c.add_argument("--settle-after", type=int, default=20_000,
                   help="peaks are taken after this step (default 20000: past the entropy-inflated start)")
    c.set_defaults(func=cmd_compare)

    k = sub.add_parser("check", help="self-test: the diagnostic-recording SAC equals stock SB3 SAC bit for bit")
    k.add_argument("--steps", type=int, default=400)
    k.add_argument("--seed", type=int, default=0)
    k.set_defaults(func=cmd_check)

    r = sub.add_parser("check-resume", help="self-test: an SB3 run killed with SIGKILL and resumed from its "
                       "checkpoint ends bit-identical to the uninterrupted run")
    r.add_argument("--steps", type=int, default=600)
    r.add_argument("--kill-after", type=int, default=400, help="checkpoint step to kill after (even, < --steps)")
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=cmd_check_resume)

    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
