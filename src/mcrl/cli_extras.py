"""Subcommands beyond training: plot, report, render, sweep."""
from __future__ import annotations

from pathlib import Path

from mcrl.cli import _EXTRA_COMMANDS


def _plot(sub) -> None:
    p = sub.add_parser("plot", help="learning curves of one run (PNG)")
    p.add_argument("run_dir")
    p.add_argument("--out", help="PNG path (default RUN_DIR/curves.png)")

    def run(args) -> int:
        from mcrl.plots import plot_run

        print(f"wrote {plot_run(args.run_dir, args.out)}")
        return 0

    p.set_defaults(func=run)


def _report(sub) -> None:
    p = sub.add_parser("report", help="statistical report of a sweep (Markdown + PNG, or HTML)")
    p.add_argument("experiment_dir")
    p.add_argument("--format", choices=("md", "html"), default="md")
    p.add_argument("--out", help="output directory (default EXPERIMENT_DIR/report)")

    def run(args) -> int:
        from mcrl.report import write_report

        print(f"wrote {write_report(args.experiment_dir, args.out, fmt=args.format)}")
        return 0

    p.set_defaults(func=run)


_EXTRA_COMMANDS.extend([_plot, _report])


def _render(sub) -> None:
    p = sub.add_parser("render", help="video of the saved policy with the MC reward timeline")
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--format", choices=("mp4", "gif"), default="mp4")
    p.add_argument("--checkpoint", type=int, metavar="STEP", help="a checkpoint's step (default: the newest)")
    p.add_argument("--out", help="video path (default RUN_DIR/videos/policy_step<STEP>.<format>)")
    p.add_argument("--fps", type=float, default=25.0)

    def run(args) -> int:
        from mcrl.render import render_run

        path = render_run(args.run_dir, episodes=args.episodes, fmt=args.format, checkpoint_step=args.checkpoint,
                          out=args.out, fps=args.fps)
        print(f"wrote {path}")
        return 0

    p.set_defaults(func=run)


_EXTRA_COMMANDS.append(_render)
