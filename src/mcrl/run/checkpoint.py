"""Checkpoints: plain .npz arrays plus JSON, never pickle, written atomically.

A checkpoint is a directory `checkpoints/step_<N>/` holding `state.npz` (every leaf of the learner's state
and of its diagnostics, keyed by its pytree path: `flatten`), `normaliser.npz` (the intrinsic reward's
normaliser's history, packed), `buffer.npz` (the replay buffer, optional) and `meta.json` (step counters, the host
RNG state, the config). `install` is the one way a checkpoint comes into being, whoever wrote its files (a run, or
the sweep driver receiving a remote run's): every file fsynced in a temporary directory, renamed into place, then
`checkpoints/latest` replaced atomically and the oldest pruned. `find` falls back to the newest complete
checkpoint when `latest` is missing or dangling, so a kill at any moment leaves an older checkpoint usable; a
write that fails (a full disk) removes its temporary directory, freeing its space, and leaves `latest` as it was.
Loading uses `numpy.load(allow_pickle=False)`: it runs no code. JAX is imported only by the functions that
handle pytrees, so the sweep driver installs checkpoints without it.
"""
from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

import mcrl.files as files
from mcrl.errors import MCRLError
from mcrl.renames import new_path
from mcrl.run import rundir

_COMPLETE = ("state.npz", "meta.json")  # a checkpoint directory without these is not usable
_OLD_FORMAT = (".actor", ".norm.")  # keys of checkpoints by mcrl 0.1 and commit 83e6d8d (flat layout)


def flatten(tree) -> dict[str, np.ndarray]:
    """The leaves of a pytree as host arrays keyed by their paths (`.pi.params['MLP_0']...`): state.npz's keys."""
    import jax

    return {jax.tree_util.keystr(path): np.asarray(leaf)
            for path, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(tree))[0]}


def install(run_dir: Path, step: int, write: Callable[[Path], None], keep: int) -> Path:
    """Make checkpoint `step` of `run_dir` from the files `write(directory)` puts into an empty directory: each
    fsynced, the directory renamed into place (one of the same step moved aside first and dropped after),
    `latest` pointed at it, all but the newest `keep` checkpoints removed."""
    ckpt_root = rundir.checkpoint_root(run_dir)
    ckpt_root.mkdir(parents=True, exist_ok=True)
    final = ckpt_root / rundir.checkpoint_name(step)
    tmp = ckpt_root / f".tmp-{final.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        write(tmp)
        for p in tmp.iterdir():
            with open(p, "rb+") as f:
                os.fsync(f.fileno())
        files.fsync_dir(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # a full disk gets its space back; `latest` still names the last
        raise
    old = ckpt_root / f".old-{final.name}"
    shutil.rmtree(old, ignore_errors=True)  # left by a kill between the two renames below
    if final.exists():  # the same step saved again (a resumed run): move the old one aside, drop it after
        os.rename(final, old)
        os.rename(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, final)
    rundir.write_latest(run_dir, final.name)
    files.fsync_dir(ckpt_root)
    for old in sorted(ckpt_root.glob("step_*"))[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def save(run_dir: Path, step: int, arrays: dict[str, np.ndarray], meta: dict[str, Any], buffer_arrays: dict | None,
         keep: int, extra: dict[str, dict[str, np.ndarray]] | None = None) -> Path:
    """Install step `step`: `arrays` (`flatten`ed pytrees) as state.npz, `extra` arrays (one `<name>.npz`
    each), the buffer and `meta`."""
    def write(d: Path) -> None:
        np.savez(d / "state.npz", **arrays)
        for name, more in (extra or {}).items():
            np.savez(d / f"{name}.npz", **more)
        if buffer_arrays is not None:
            np.savez(d / "buffer.npz", **buffer_arrays)
        files.write_json(d / "meta.json", {**meta, "step": step, "has_buffer": buffer_arrays is not None})

    return install(run_dir, step, write, keep)


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


def restore_state(ckpt: Path, template, optional=None):
    """(template, optional) filled with the checkpoint's arrays, each a freshly initialised pytree of the run's
    config: every leaf of `template` must be there; a leaf of `optional` that is not keeps its initial value. Keys
    from before a rename are read under today's names (`mcrl.renames.new_path`)."""
    import jax

    arrays = {new_path(k): v for k, v in _load_npz(ckpt / "state.npz").items()}
    if any(k.startswith(_OLD_FORMAT) for k in arrays):
        raise MCRLError(f"checkpoint {ckpt} was written by an older mcrl (0.1 or commit 83e6d8d): convert it with "
                        "`python scripts/migrate_checkpoint.py RUN_DIR` (docs/run-directory.md)")

    def fill(tree, required: bool):
        leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
        new_leaves = []
        for path, leaf in leaves:
            key = jax.tree_util.keystr(path)
            if key not in arrays:
                if not required:
                    new_leaves.append(leaf)
                    continue
                raise MCRLError(f"checkpoint {ckpt} lacks {key}: it was written by a different config "
                                "(e.g. with/without intrinsic models); resume with the run's own config.json")
            a = arrays.pop(key)
            if a.shape != np.shape(leaf) or a.dtype != np.asarray(leaf).dtype:
                raise MCRLError(f"checkpoint {ckpt}: {key} has shape {a.shape} {a.dtype}, expected {np.shape(leaf)} "
                                f"{np.asarray(leaf).dtype}: the network sizes differ from the config")
            new_leaves.append(jax.numpy.asarray(a))
        return jax.tree_util.tree_unflatten(treedef, new_leaves)

    state = fill(template, True)
    extra = fill(optional, False) if optional is not None else None
    if arrays:
        raise MCRLError(f"checkpoint {ckpt} has arrays this config does not ({sorted(arrays)[:3]}...): "
                        "resume with the run's own config.json")
    return state, extra


def load_extra(ckpt: Path, name: str) -> dict[str, np.ndarray] | None:
    """The arrays `save` wrote as `extra[name]`, or None if the checkpoint has none."""
    path = ckpt / f"{name}.npz"
    return _load_npz(path) if path.is_file() else None


def load_buffer_arrays(ckpt: Path) -> dict[str, np.ndarray] | None:
    path = ckpt / "buffer.npz"
    return _load_npz(path) if path.is_file() else None
