"""Convert a checkpoint written by an older mcrl into today's format, the one `mcrl train --resume` reads.

    python scripts/migrate_checkpoint.py CKPT_DIR [--out NEW_DIR]
    python scripts/migrate_checkpoint.py RUN_DIR  [--out NEW_RUN_DIR]

Two older formats are converted (a checkpoint already in today's format is left as it is):

- commit 83e6d8d (the flat module layout, before `algo/` and `run/`): `state.npz` keys each part of the
  learner twice, parameters and optimiser state apart (`.actor`, `.actor_opt[0]...`, `.critic`, `.critic_opt`,
  `.critic_target`, `.log_ent_coef`, `.ent_opt`, `.mc`, `.mc_opt`); the normaliser is in `normaliser.npz`.
  Today the two travel together (`.pi.params`, `.pi.opt`, ...); the arrays are the same, only renamed.
- mcrl 0.1: the same keys, and the MC normaliser inside `state.npz` (`.norm.ring`, `.norm.ptr`,
  `.norm.count`, `.norm.c1..c3`) as a window of `mc_history` KL values. Its `config.json` has no `init`
  (those runs used Flax's initialisation) and counted `mc_history` in KL values. The window becomes
  `normaliser.npz` (its newest values, in order, for the window of `mc_history // values per step` gradient
  steps), and the config gets `init=flax` and `mc_history` in gradient steps. A resumed 0.1 run trains with
  today's code, so it continues the 0.1 run, it does not replay what 0.1 would have done.

Given a run directory (it has `config.json` and `checkpoints/`), its `config.json` and every checkpoint are
converted. Without `--out` the conversion is in place: each checkpoint is written beside the old one under a
temporary name and renamed over it, so a kill leaves the old or the new one, never half of one. With `--out`
the source is only read. From Python (studies/sb3-parity/transplant.py does this)::

    from migrate_checkpoint import migrate          # with scripts/ on sys.path
    new_ckpt = migrate(Path("old/checkpoints/step_000010000"), Path("/tmp/step_000010000"))
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

# 83e6d8d's and 0.1's train-state keys -> today's; longest first, so `.critic_target` is not read as `.critic`
RENAMED = ((".critic_target", ".q_target"), (".critic_opt", ".q.opt"), (".critic", ".q.params"),
           (".actor_opt", ".pi.opt"), (".actor", ".pi.params"), (".ent_opt", ".ent.opt"),
           (".log_ent_coef", ".ent.params"), (".mc_opt", ".intrinsic.opt"), (".mc", ".intrinsic.params"))
NORM_01 = ".norm."  # mcrl 0.1 kept the normaliser inside state.npz
_L3 = 1 << 23  # finest histogram level of mcrl.algo.normaliser (top 24 bits of the float32 pattern)


class MigrationError(Exception):
    pass


def current_key(key: str) -> str:
    """Today's name of a 83e6d8d / 0.1 `state.npz` key (others are unchanged)."""
    for old, new in RENAMED:
        if key == old or key.startswith(old + "[") or key.startswith(old + "."):
            return new + key[len(old):]
    return key


def format_of(keys) -> str:
    """'0.1', '83e6d8d' or 'current', from the keys of a checkpoint's state.npz."""
    roots = {k.split("[")[0] for k in keys}
    if not roots & {".actor", ".actor_opt"}:
        return "current"
    return "0.1" if any(k.startswith(NORM_01) for k in keys) else "83e6d8d"


def migrate_config(d: dict) -> dict:
    """A run config (config.json or meta.json's "config") in today's terms: 0.1's gets `init=flax` and
    `mc_history` in gradient steps; keys added since take their defaults."""
    d = dict(d)
    if "init" not in d and "mc_history" in d:  # mcrl 0.1: every config.json it wrote lists mc_history
        d["init"] = "flax"
        if d["mc_history"] is not None:
            per_step = 1 if d.get("mc_reduction") == "batch" else int(d.get("batch_size", 256))
            d["mc_history"] = max(1, int(d["mc_history"]) // per_step)
    from mcrl.config import Config  # no JAX: fills in the keys added since, and validates
    from mcrl.errors import MCRLError

    try:
        return Config.from_dict(d).to_dict()
    except MCRLError as e:
        raise MigrationError(f"its config does not fit today's mcrl: {e}") from None


def window_capacity(cfg: dict) -> int:
    """KL values the normaliser's window holds under a (migrated) config; 0 = the whole run, no ring."""
    from mcrl.renames import new_names

    history = new_names(cfg).get("intrinsic_history")  # either name (mcrl.renames)
    if history is None:
        return 0
    per_step = 1 if cfg.get("mc_reduction") == "batch" else int(cfg["batch_size"])
    return int(history) * per_step


def normaliser_from_01(arrays: dict[str, np.ndarray], capacity: int) -> dict[str, np.ndarray]:
    """`normaliser.npz` (mcrl.algo.normaliser.pack's format) from 0.1's in-state ring: its values oldest
    first, the newest `capacity` of them kept (all for capacity 0: a whole-run history)."""
    ring = np.asarray(arrays[NORM_01 + "ring"], np.float32)
    ptr, count = int(arrays[NORM_01 + "ptr"]), int(arrays[NORM_01 + "count"])
    values = ring[:count] if count < ring.shape[0] else np.concatenate([ring[ptr:], ring[:ptr]])
    if capacity == ring.shape[0]:  # the same window: the ring as it was, so the run goes on bit for bit
        values, new_ring, new_ptr = ring[:count], ring, ptr
    elif capacity:
        values = values[-capacity:]
        new_ring = np.zeros(capacity, np.float32)
        new_ring[: len(values)] = values
        new_ptr = len(values) % capacity
    else:
        new_ring, new_ptr = np.zeros(0, np.float32), 0
    keys = (np.maximum(values, 0.0).astype(np.float32).view(np.uint32) >> 8).astype(np.int64)
    c3 = np.bincount(keys, minlength=_L3).astype(np.int32)
    nz = np.flatnonzero(c3).astype(np.int32)
    return {"ring": new_ring, "ptr": np.asarray(new_ptr, np.int32), "count": np.asarray(len(values), np.int32),
            "c3_index": nz, "c3_count": c3[nz]}


def _load(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())


def _write_json(path: Path, obj: dict, indent: int | None = None) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(json.dumps(obj, indent=indent, sort_keys=indent is not None))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _copy(src: Path, dst: Path) -> None:
    shutil.copyfile(src, dst)
    with open(dst, "rb+") as f:
        os.fsync(f.fileno())


def _convert_into(src: Path, tmp: Path) -> str:
    """Write the converted checkpoint `src` into the empty directory `tmp`; the source's format."""
    if not (src / "state.npz").is_file() or not (src / "meta.json").is_file():
        raise MigrationError(f"{src} is not a checkpoint directory (no state.npz and meta.json)")
    arrays = _load(src / "state.npz")
    fmt = format_of(arrays)
    meta = json.loads((src / "meta.json").read_text())
    if "config" in meta:
        meta["config"] = migrate_config(meta["config"])
    state = {current_key(k): v for k, v in arrays.items() if not k.startswith(NORM_01)}
    _write_npz(tmp / "state.npz", state)
    if fmt == "0.1" and NORM_01 + "ring" in arrays:
        if "config" not in meta:
            raise MigrationError(f"{src}/meta.json has no config: the normaliser's window size is unknown")
        _write_npz(tmp / "normaliser.npz", normaliser_from_01(arrays, window_capacity(meta["config"])))
    for p in sorted(src.iterdir()):  # normaliser.npz (83e6d8d), buffer.npz and anything else, unchanged
        if p.is_file() and p.name not in ("state.npz", "meta.json") and not (tmp / p.name).exists():
            _copy(p, tmp / p.name)
    if fmt != "current":
        meta["migrated_from"] = fmt
    _write_json(tmp / "meta.json", meta)
    return fmt


def migrate(src: Path, dst: Path) -> Path:
    """Convert checkpoint directory `src` into today's format at `dst` (`dst == src`: in place); `dst`."""
    src, dst = Path(src), Path(dst)
    in_place = dst.resolve() == src.resolve()
    if not in_place and dst.exists():
        raise MigrationError(f"{dst} exists: give a new directory for the converted checkpoint")
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.parent / f".tmp-migrate-{dst.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        _convert_into(src, tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if in_place:
        old = dst.parent / f".old-migrate-{dst.name}"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(dst, old)
        os.rename(tmp, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, dst)
    return dst


def migrate_run(src: Path, dst: Path) -> Path:
    """Convert a run directory: its config.json and every checkpoint (`dst == src`: in place); `dst`."""
    src, dst = Path(src), Path(dst)
    if dst.resolve() != src.resolve():
        if dst.exists():
            raise MigrationError(f"{dst} exists: give a new directory for the converted run")
        shutil.copytree(src, dst, ignore=shutil.ignore_patterns("step_*"))
        for ck in sorted((src / "checkpoints").glob("step_*")):
            migrate(ck, dst / "checkpoints" / ck.name)
    else:
        for ck in sorted((src / "checkpoints").glob("step_*")):
            migrate(ck, ck)
    cfg = json.loads((dst / "config.json").read_text())
    _write_json(dst / "config.json", migrate_config(cfg), indent=2)
    return dst


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", type=Path, help="a checkpoint directory (checkpoints/step_<N>) or a run directory")
    p.add_argument("--out", type=Path, help="write the converted copy here (default: convert in place)")
    args = p.parse_args(argv)
    src = args.src
    try:
        if (src / "checkpoints").is_dir() and (src / "config.json").is_file():
            out = migrate_run(src, args.out or src)
        elif (src / "state.npz").is_file():
            with np.load(src / "state.npz", allow_pickle=False) as f:
                fmt = format_of(f.files)
            out = migrate(src, args.out or src)
            print(f"{src}: {fmt} format" + ("" if fmt == "current" else " -> today's"))
        else:
            raise MigrationError(f"{src} is neither a checkpoint directory (state.npz, meta.json) nor a run "
                                 "directory (config.json, checkpoints/)")
    except (MigrationError, OSError, ValueError) as e:
        print(f"migrate_checkpoint: error: {e}", file=sys.stderr)
        return 2
    print(f"converted: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
