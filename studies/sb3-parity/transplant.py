"""Continue one run's learning state (weights, target critics, Adam states, entropy coefficient, replay buffer)
under mcrl and under stable-baselines3 (SB3), with fresh random streams: whose instability is it?

Subcommands (run from the repository root; needs the ``bench`` extra)::

    python studies/sb3-parity/transplant.py continue --from CKPT --system {mcrl,sb3} --stream K [--steps 20000] \
        --out DIR
    python studies/sb3-parity/transplant.py check --from MCRL_CKPT [--sb3-from SB3_CKPT]
    python studies/sb3-parity/transplant.py summary DIR... [--reference LABEL=RUN_DIR] [--out table.md]

``CKPT`` is an mcrl checkpoint directory (``checkpoints/step_<N>/`` of today's format or commit 83e6d8d's) or an
SB3 parity checkpoint (``sb3_checkpoints/step_<N>/`` of ``studies/sb3-parity/parity_sb3.py``; its run's config.json
is looked up in it and up to two directories above, or given with ``--config``).

``continue`` writes DIR as a run directory in mcrl's format (config.json, metrics.csv with a row every 1,000
steps, eval.csv, final_eval.json) plus transplant.json (origin, system, stream, steps, versions); stream K seeds
every random stream of the continuation (``stream_seed(K)``). mcrl continues through ``mcrl train --resume DIR``,
SB3 through ``_sb3.py``'s ParitySAC. ``check`` verifies that the state moves exactly both ways and that one
gradient step from it agrees; ``summary`` tabulates continuations. What moves, how each system continues, and
the results: docs/studies/sb3-parity.md, "Whose instability? The transplant test".
"""
from __future__ import annotations

import _common

_common.one_thread()  # the machine is shared with long experiments; before jax / torch load

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from _transplant import TransplantError, is_mcrl_checkpoint  # noqa: E402
from mcrl.errors import MCRLError  # noqa: E402

LOG_EVERY = 1_000
FINAL_EVAL_EPISODES = 10
_STREAM_SALT = 0x7A5  # keeps stream seeds apart from the small seeds the origin runs used


def stream_seed(stream: int) -> int:
    """The one seed behind every random stream of continuation `stream` (< 2**31, for JAX and SB3 alike)."""
    return int(np.random.SeedSequence([_STREAM_SALT, stream]).generate_state(1)[0] >> 1)


# ----------------------------------------------------------------------------------------- origins

@dataclasses.dataclass
class Origin:
    path: Path
    system: str  # "mcrl" or "sb3"
    label: str  # run name @ step
    cfg: object  # mcrl Config of the origin run
    step: int


def _sb3_config(ckpt: Path, config: Path | None) -> Path:
    for p in ([config] if config else [ckpt / "config.json", ckpt.parent / "config.json",
                                        ckpt.parent.parent / "config.json"]):
        if p is not None and p.is_file():
            return p
    raise TransplantError(f"no config.json for the SB3 checkpoint {ckpt}: pass --config RUN_DIR/config.json "
                          "(the SB3 run's own)")


def open_origin(path: Path, config: Path | None = None) -> Origin:
    from mcrl.config import Config

    path = Path(path)
    run = path.parent.parent.name if path.parent.name in ("checkpoints", "sb3_checkpoints") else path.parent.name
    if is_mcrl_checkpoint(path):
        meta = json.loads((path / "meta.json").read_text())
        cfg = meta.get("config") or json.loads(_sb3_config(path, config).read_text())
        return Origin(path, "mcrl", f"mcrl {run} @ {meta['step'] // 1000}k", Config.from_run_json(cfg), meta["step"])
    if (path / "model.zip").is_file() and (path / "replay_buffer.pkl").is_file():
        cfg = Config.from_run_json(json.loads(_sb3_config(path, config).read_text()))
        step = int(path.name.split("_")[-1]) if path.name.startswith("step_") else -1
        return Origin(path, "sb3", f"SB3 {run} @ {step // 1000}k", cfg, step)
    raise TransplantError(f"{path} is neither an mcrl checkpoint (state.npz + meta.json) nor an SB3 parity "
                          "checkpoint (model.zip + replay_buffer.pkl): give a checkpoints/step_<N> directory")


def origin_learning(origin: Origin):
    """(Learning, the loaded SB3 model or None) of an origin."""
    from _transplant import load_sb3_checkpoint, read_mcrl, read_sb3

    if origin.system == "mcrl":
        return read_mcrl(origin.path)[0], None
    model, episode = load_sb3_checkpoint(origin.path, origin.cfg)
    return read_sb3(model, episode=episode), model


def continuation_config(cfg, stream: int, total_steps: int):
    return dataclasses.replace(cfg, seed=stream_seed(stream), total_steps=total_steps, eval_every=0,
                               log_every=LOG_EVERY, final_eval_episodes=FINAL_EVAL_EPISODES,
                               checkpoint_every=10 * total_steps, keep_checkpoints=1, video_every=0)


def versions() -> dict:
    """Package versions, the mcrl source that runs (a git checkout's commit and whether src/mcrl has local
    changes, or the COMMIT file of an exported snapshot beside its src/) and the CPU."""
    import importlib.metadata as md

    import mcrl as lib

    out = {p: md.version(p) for p in ("jax", "numpy", "torch", "stable_baselines3", "gymnasium", "mujoco")
           if _installed(p)}
    src = Path(lib.__file__).resolve().parent
    out["mcrl_source"] = str(src)
    root = src.parent.parent
    if (root / "COMMIT").is_file():
        out["mcrl_commit"] = (root / "COMMIT").read_text().strip()
    else:
        git = ["git", "-C", str(root)]
        try:
            out["mcrl_commit"] = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True, text=True,
                                                check=True).stdout.strip()
            out["mcrl_src_modified"] = bool(subprocess.run(git + ["status", "--porcelain", "src/mcrl"],
                                                           capture_output=True, text=True).stdout.strip())
        except (OSError, subprocess.CalledProcessError):
            pass
    cpu = _common.cpu_label()
    if cpu is not None:
        out["cpu"] = cpu
    return out


def _installed(dist: str) -> bool:
    import importlib.metadata as md

    try:
        md.version(dist)
        return True
    except md.PackageNotFoundError:
        return False


# ----------------------------------------------------------------------------------------- continue

def continue_mcrl(origin: Origin, cfg, out: Path, learning) -> None:
    """Today's checkpoint + config.json into `out`, then mcrl's CLI continues it."""
    from _transplant import write_mcrl

    write_mcrl(out, learning, cfg)
    env = {**os.environ, **_common.ONE_THREAD}
    with open(out / "train.log", "w") as log:
        subprocess.run([sys.executable, "-m", "mcrl.cli", "train", "--resume", str(out), "--no-progress"],
                       env=env, stdout=log, stderr=subprocess.STDOUT, check=True)


def continue_sb3(origin: Origin, cfg, out: Path, learning, model) -> None:
    """ParitySAC from the state (SB3's own loaded model for an SB3 origin), re-seeded, continued in-process."""
    import torch

    torch.set_num_threads(1)
    import stable_baselines3

    from _sb3 import Evaluator, _make_recorder, build_model
    from _transplant import install_sb3
    from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS, start_csv

    if model is None:  # an mcrl origin: a fresh SB3 SAC at the run's settings, given the state
        model, _ = build_model(cfg)
        install_sb3(model, learning)
    model.set_random_seed(cfg.seed)  # torch, numpy, Python, action space, and the env's next reset
    model._last_obs = None  # learn() starts with a fresh (seeded) episode
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(cfg.to_json())
    (out / "peer.json").write_text(json.dumps({"system": "stable-baselines3", "version": stable_baselines3.__version__,
                                               "torch": torch.__version__, "torch_threads": 1}) + "\n")
    for name, cols in (("metrics.csv", METRIC_COLUMNS), ("eval.csv", EVAL_COLUMNS)):
        start_csv(out / name, cols)
    evaluator = Evaluator(cfg)
    rec = {"step": learning.step, "episodes": learning.episode, "eval_round": 0, "elapsed": 0.0}
    recorder = _make_recorder(cfg, out, model, evaluator, False, rec, checkpoints=False)
    try:
        model.learn(total_timesteps=cfg.total_steps - learning.step, callback=recorder, reset_num_timesteps=False)
    finally:
        evaluator.close()
        model.get_env().close()


def cmd_continue(args) -> int:
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise TransplantError(f"{out} exists and is not empty: choose a new --out for each continuation")
    if args.steps < LOG_EVERY:
        raise TransplantError(f"--steps {args.steps} is shorter than one log interval ({LOG_EVERY})")
    origin = open_origin(Path(args.origin), args.config)
    learning, model = origin_learning(origin)
    if args.system == "mcrl":
        model = None
    cfg = continuation_config(origin.cfg, args.stream, learning.step + args.steps)
    out.mkdir(parents=True, exist_ok=True)
    info = {"origin": str(origin.path.resolve()), "origin_label": origin.label, "origin_system": origin.system,
            "origin_step": learning.step, "system": args.system, "stream": args.stream, "seed": cfg.seed,
            "steps": args.steps, "fresh_episode": True, "versions": versions(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    _common.write_json(out / "transplant.json", info)
    t0 = time.time()
    if args.system == "mcrl":
        continue_mcrl(origin, cfg, out, learning)
    else:
        continue_sb3(origin, cfg, out, learning, model)
    info.update(finished=time.strftime("%Y-%m-%dT%H:%M:%S"), wall_s=round(time.time() - t0, 1))
    _common.write_json(out / "transplant.json", info)
    print(f"{origin.label} continued under {args.system}, stream {args.stream}: {out / 'metrics.csv'}")
    return 0


# ----------------------------------------------------------------------------------------- check

def cmd_check(args) -> int:
    from _sb3 import build_model, make_parity_sac_class  # noqa: F401
    from _transplant_check import run_check

    import torch

    torch.set_num_threads(1)
    origin = open_origin(Path(args.origin), args.config)
    if origin.system != "mcrl":
        raise TransplantError("check --from takes an mcrl checkpoint (the SB3 one goes to --sb3-from)")
    learning, _ = origin_learning(origin)
    if args.sb3_origin:
        sb3 = open_origin(Path(args.sb3_origin), args.sb3_config)
        sb3_learning, sb3_model = origin_learning(sb3)
        sb3_cfg, episode, label = sb3.cfg, sb3_learning.episode, sb3.label
    else:  # a short SB3 run of the same settings: trained weights, moments and a buffer of whole episodes
        sb3_cfg = dataclasses.replace(origin.cfg, total_steps=args.sb3_steps)
        sb3_model, _ = build_model(sb3_cfg)
        sb3_model.learn(total_timesteps=args.sb3_steps)
        episode, label = args.sb3_steps // 50, f"SB3 trained {args.sb3_steps} steps in-process"
    t0 = time.time()
    res = run_check(learning, origin.cfg, sb3_model, sb3_cfg, episode, steps=args.steps)
    res.update(mcrl_origin=origin.label, sb3_origin=label, seconds=round(time.time() - t0, 1))
    for part in ("mcrl_sb3_mcrl", "mcrl_files_mcrl", "sb3_files_mcrl", "sb3_mcrl_sb3"):
        worst = max(res[part].values())
        print(f"{part}: {len(res[part])} arrays compared, max |difference| {worst:g}")
    for r in res["one_step"]:
        L = r["losses"]
        print(f"{r['origin']} origin, {r['steps']} gradient steps, {r['mode']}: critic loss {L['critic_loss']['mcrl']:.6g} / "
              f"{L['critic_loss']['sb3']:.6g}, q_mean {L['q_mean']['mcrl']:.6g} / {L['q_mean']['sb3']:.6g}; "
              "max rel loss diff " + ", ".join(f"{k} {v['max_rel']:.1e}" for k, v in L.items())
              + "; update rel L2 " + ", ".join(f"{g} {v:.1e}" for g, v in r["update_rel_l2"].items())
              + "; Adam moments rel L2 " + ", ".join(f"{g} {v:.1e}" for g, v in r["adam_rel_l2"].items()))
    print("PASS" if res["pass"] else f"FAIL: {res['not_exact']} {res['step_failures']}")
    if args.json:
        _common.write_json(args.json, res, default=float)
    return 0 if res["pass"] else 1


# ----------------------------------------------------------------------------------------- summary

from _transplant_summary import cmd_summary  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("continue", help="continue a checkpoint's learning state under one system")
    c.add_argument("--from", dest="origin", required=True, metavar="CKPT")
    c.add_argument("--system", choices=("mcrl", "sb3"), required=True)
    c.add_argument("--stream", type=int, required=True, metavar="K", help="the continuation's random streams")
    c.add_argument("--steps", type=int, default=20_000, help="environment steps to continue (default 20,000)")
    c.add_argument("--out", required=True, metavar="DIR", help="a new directory for this continuation")
    c.add_argument("--config", type=Path, help="an SB3 checkpoint's run config.json (default: looked up)")
    k = sub.add_parser("check", help="the conversion is exact both ways, and one gradient step agrees")
    k.add_argument("--from", dest="origin", required=True, metavar="MCRL_CKPT")
    k.add_argument("--config", type=Path)
    k.add_argument("--sb3-from", dest="sb3_origin", metavar="SB3_CKPT",
                   help="an SB3 parity checkpoint for the SB3 -> mcrl -> SB3 part (default: a short SB3 run)")
    k.add_argument("--sb3-config", type=Path)
    k.add_argument("--sb3-steps", type=int, default=600, help="steps of the in-process SB3 run (default 600)")
    k.add_argument("--steps", type=int, default=3, help="gradient steps of the side-by-side step (default 3)")
    k.add_argument("--json", help="write every number to this file")
    s = sub.add_parser("summary", help="peaks and final values per origin and system, as a Markdown table")
    s.add_argument("dirs", nargs="+", metavar="DIR")
    s.add_argument("--reference", action="append", default=[], metavar="LABEL=RUN_DIR",
                   help="also show the origin run's own course over the same steps (LABEL as in transplant.json)")
    s.add_argument("--out", help="write the table to this Markdown file too")
    args = ap.parse_args(argv)
    try:
        return {"continue": cmd_continue, "check": cmd_check, "summary": cmd_summary}[args.cmd](args)
    except (TransplantError, MCRLError) as e:
        print(f"mcrl: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
