"""Checkpoints: plain .npz arrays plus JSON, never pickle, written atomically.

A checkpoint is a directory `checkpoints/step_<N>/` holding `state.npz` (every leaf of the train
state, keyed by its pytree path), `normaliser.npz` (the MC normaliser's history, packed), `buffer.npz`
(the replay buffer, optional) and `meta.json` (step counters, the host RNG state, the config). Every
file is fsynced; the directory is written under a temporary name and renamed into place, then
`checkpoints/latest` is replaced atomically. `find` falls back to the newest complete checkpoint when
`latest` is missing or dangling, so a kill at any moment leaves an older checkpoint usable. Loading uses
`numpy.load(allow_pickle=False)`: it runs no code.
"""
from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mcrl.errors import MCRLError
from mcrl.run import rundir

_COMPLETE = ("state.npz", "meta.json")  # a checkpoint directory without these is not usable
_OLD_FORMAT = (".actor", ".norm.")  # keys of checkpoints by mcrl 0.1 and commit 83e6d8d (flat layout)


def _flatten(tree) -> dict[str, np.ndarray]:
    return {jax.tree_util.keystr(path): np.asarray(leaf)
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())


def _write_text(path: Path, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def save(run_dir: Path, step: int, state, meta: dict[str, Any], buffer_arrays: dict | None, keep: int,
         extra: dict[str, dict[str, np.ndarray]] | None = None) -> Path:
    """Write `state` (a pytree), `extra` arrays (one `<name>.npz` each), the buffer and `meta` as step `step`."""
    ckpt_root = rundir.checkpoint_root(run_dir)
    ckpt_root.mkdir(parents=True, exist_ok=True)
    final = ckpt_root / rundir.checkpoint_name(step)
    tmp = ckpt_root / f".tmp-{final.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    _write_npz(tmp / "state.npz", _flatten(jax.device_get(state)))
    for name, arrays in (extra or {}).items():
        _write_npz(tmp / f"{name}.npz", arrays)
    if buffer_arrays is not None:
        _write_npz(tmp / "buffer.npz", buffer_arrays)
    _write_text(tmp / "meta.json", json.dumps({**meta, "step": step, "has_buffer": buffer_arrays is not None}))
    _fsync_dir(tmp)
    if final.exists():  # the same step saved again (a resumed run): move the old one aside, drop it after
        old = ckpt_root / f".old-{final.name}"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(final, old)
        os.rename(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, final)
    rundir.write_latest(run_dir, final.name)
    _fsync_dir(ckpt_root)
    for old in sorted(ckpt_root.glob("step_*"))[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def find(run_dir: Path, step: int | None = None) -> Path:
    """The newest complete checkpoint (or the one at `step`)."""
    ckpt_root = rundir.checkpoint_root(run_dir)
    if step is not None:
        path = ckpt_root / rundir.checkpoint_name(step)
        if not path.is_dir():
            have = sorted(p.name for p in ckpt_root.glob("step_*"))
            raise MCRLError(f"no checkpoint at step {step} in {run_dir}: available: {', '.join(have) or 'none'}")
        return path
    latest = rundir.latest_checkpoint(run_dir)
    if latest is not None and is_complete(ckpt_root / latest):
        return ckpt_root / latest
    # `latest` missing or dangling (a kill between two renames): the newest complete checkpoint instead
    for path in sorted(ckpt_root.glob("step_*"), reverse=True):
        if is_complete(path):
            return path
    raise MCRLError(f"{run_dir} has no checkpoint: train it (longer than checkpoint_every steps) first")


def is_complete(path: Path) -> bool:
    return path.is_dir() and all((path / f).is_file() for f in _COMPLETE)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise MCRLError(f"unreadable checkpoint file {path} ({type(e).__name__}): it is corrupt; delete that "
                        "checkpoint directory to fall back to an older one, or start a new run") from None


def load_meta(ckpt: Path) -> dict[str, Any]:
    try:
        return json.loads((ckpt / "meta.json").read_text())
    except (OSError, ValueError) as e:
        raise MCRLError(f"unreadable checkpoint metadata {ckpt / 'meta.json'} ({type(e).__name__}): the checkpoint "
                        "is corrupt; delete it to fall back to an older one") from None


def restore_state(ckpt: Path, template):
    """Fill `template` (a freshly initialised state of the same config) with the checkpoint's arrays."""
    arrays = _load_npz(ckpt / "state.npz")
    if any(k.startswith(_OLD_FORMAT) for k in arrays):
        raise MCRLError(f"checkpoint {ckpt} was written by an older mcrl (0.1 or commit 83e6d8d): convert it with "
                        "`python scripts/migrate_checkpoint.py RUN_DIR` (docs/run-directory.md)")
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    new_leaves = []
    for path, leaf in leaves:
        key = jax.tree_util.keystr(path)
        if key not in arrays:
            raise MCRLError(f"checkpoint {ckpt} lacks {key}: it was written by a different config "
                            "(e.g. with/without MC models); resume with the run's own config.json")
        a = arrays.pop(key)
        if a.shape != np.shape(leaf) or a.dtype != np.asarray(leaf).dtype:
            raise MCRLError(f"checkpoint {ckpt}: {key} has shape {a.shape} {a.dtype}, expected "
                            f"{np.shape(leaf)} {np.asarray(leaf).dtype}: the network sizes differ from the config")
        new_leaves.append(a)
    if arrays:
        raise MCRLError(f"checkpoint {ckpt} has arrays this config does not ({sorted(arrays)[:3]}...): "
                        "resume with the run's own config.json")
    return jax.tree_util.tree_unflatten(treedef, [jax.numpy.asarray(x) for x in new_leaves])


def load_extra(ckpt: Path, name: str) -> dict[str, np.ndarray] | None:
    """The arrays `save` wrote as `extra[name]`, or None if the checkpoint has none."""
    path = ckpt / f"{name}.npz"
    return _load_npz(path) if path.is_file() else None


def load_buffer_arrays(ckpt: Path) -> dict[str, np.ndarray] | None:
    path = ckpt / "buffer.npz"
    return _load_npz(path) if path.is_file() else None
