"""The `mcrl` command line. Every user error ends in one line on stderr and exit code 2."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from mcrl.errors import MCRLError

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
    from mcrl import trainer
    from mcrl.config import resolve_config

    if args.resume:
        if args.preset or args.env or args.set:
            raise MCRLError("--resume continues a run with its own config.json: drop --preset/--env/--set")
        run_dir = trainer.resume(args.resume, progress=not args.no_progress, total_steps=args.steps)
    else:
        preset = args.preset or (None if args.env else DEFAULT_PRESET)
        cfg = resolve_config(preset, _overrides(args))
        run_dir = trainer.train(cfg, args.run_dir, progress=not args.no_progress)
    done = run_dir / "done"
    summary = json.loads(done.read_text()) if done.exists() else {}
    print(f"run directory: {run_dir}")
    if summary:
        sr = summary.get("success_rate")
        print(f"final evaluation: success rate {sr if sr is None else f'{sr:.2f}'}, "
              f"mean return {summary.get('mean_return'):.2f}")
    print(f"metrics: {run_dir / 'metrics.csv'}, {run_dir / 'eval.csv'}; TensorBoard: tensorboard --logdir {run_dir}")
    return 0


def cmd_eval(args) -> int:
    from mcrl.trainer import evaluate_run

    res = evaluate_run(args.run_dir, episodes=args.episodes, checkpoint=args.checkpoint)
    sr = res["success_rate"]
    print(f"episodes: {res['episodes']}  success rate: {'n/a' if sr is None else f'{sr:.3f}'}  "
          f"mean return: {res['mean_return']:.3f}")
    return 0


def cmd_presets(args) -> int:
    from mcrl.config import PRESETS, Config, resolve_config

    if args.keys:
        for k, v in Config().to_dict().items():
            print(f"{k} = {v!r}")
        return 0
    if args.name:
        print(resolve_config(args.name).to_json())
        return 0
    width = max(map(len, PRESETS))
    for name, (desc, _) in PRESETS.items():
        print(f"{name:<{width}}  {desc}")
    return 0


def _load_transitions(path: str):
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise MCRLError(f"data file {path} not found: give an .npz with arrays states, actions, next_states")
    try:
        with np.load(p, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as e:  # a corrupt or non-npz file
        raise MCRLError(f"cannot read {path} as .npz ({type(e).__name__}): save it with numpy.savez") from None
    missing = [k for k in ("states", "actions", "next_states") if k not in arrays]
    if missing:
        raise MCRLError(f"{path} lacks array(s) {missing}: it needs states (N, ds), actions (N, da), next_states (N, ds)")
    s, a, s2 = (np.asarray(arrays[k]) for k in ("states", "actions", "next_states"))
    if s.ndim != 2 or a.ndim != 2 or s2.ndim != 2:
        raise MCRLError(f"{path}: states {s.shape}, actions {a.shape}, next_states {s2.shape} must all be 2-d "
                        "(N, dim); reshape them")
    if not (len(s) == len(a) == len(s2)) or s.shape[1] != s2.shape[1]:
        raise MCRLError(f"{path}: states {s.shape}, actions {a.shape}, next_states {s2.shape} disagree: need the "
                        "same N everywhere and next_states shaped like states")
    if len(s) < 10:
        raise MCRLError(f"{path} holds {len(s)} transitions: measuring MC needs at least 10 (thousands for accuracy)")
    if not all(np.isfinite(x).all() for x in (s, a, s2)):
        raise MCRLError(f"{path} contains NaN or inf values: clean the data first")
    return s, a, s2


def cmd_measure(args) -> int:
    import numpy as np

    from mcrl.mc import measure

    s, a, s2 = _load_transitions(args.data)
    if args.out and Path(args.out).suffix not in (".npy", ".csv"):
        raise MCRLError(f"--out {args.out}: use a .npy or .csv file name")
    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=args.max_steps, unit="step", desc="fitting MC models", mininterval=1.0)

    def progress(t, loss):
        bar.n = t
        bar.set_postfix(heldout_nll=f"{loss:.4f}")

    res = measure(s, a, s2, hidden=tuple(args.hidden), lr=args.lr, batch_size=args.batch_size,
                  max_steps=args.max_steps, seed=args.seed, progress=progress if bar else None)
    if bar:
        bar.close()
    print(f"mean MC (KL per transition): {res.mean_kl:.6f} nats  "
          f"[held-out NLL {res.heldout_nll:.4f} at step {res.steps}, {len(s)} transitions]")
    if args.out:
        out = Path(args.out)
        tmp = out.with_name(out.name + ".tmp")
        if out.suffix == ".csv":
            np.savetxt(tmp, res.per_transition_kl, header="kl_nats", comments="", fmt="%.8g")
        else:
            with open(tmp, "wb") as f:
                np.save(f, res.per_transition_kl)
        os.replace(tmp, out)
        print(f"per-transition KL written to {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mcrl", description="SAC-MC: reinforcement learning with morphological "
                                "computation as an intrinsic reward")
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train SAC / SAC-MC (default preset: fetchreach-sacmc)")
    t.add_argument("--preset", help="a preset name (`mcrl presets`)")
    t.add_argument("--env", help="any gymnasium id with a Box action space (overrides the preset's env)")
    t.add_argument("--seed", type=int)
    t.add_argument("--steps", type=int, help="total environment steps")
    t.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    t.add_argument("--run-dir", type=Path, help="where to write the run (default: runs/<preset>-s<seed>-<time>)")
    t.add_argument("--out-dir", help="parent of the default run directory")
    t.add_argument("--resume", metavar="RUN_DIR", help="continue a killed run from its newest checkpoint")
    t.add_argument("--video-every", type=int, help="record an evaluation video every N steps")
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="re-evaluate a saved policy (deterministic actions)")
    e.add_argument("run_dir")
    e.add_argument("--episodes", type=int)
    e.add_argument("--checkpoint", type=int, metavar="STEP")
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

    for extra in _EXTRA_COMMANDS:
        extra(sub)
    return p


_EXTRA_COMMANDS: list = []  # filled by modules that add subcommands (render, plot, sweep, report)


def _register_extras() -> None:
    from mcrl import cli_extras  # noqa: F401  (registers its commands)


def main(argv: list[str] | None = None) -> int:
    _register_extras()
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MCRLError as e:
        print(f"mcrl: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mcrl: interrupted; a run continues with `mcrl train --resume RUN_DIR`", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # Under `python -m`, this file runs as __main__; extra commands register into the importable mcrl.cli.
    from mcrl.cli import main as _main

    sys.exit(_main())
