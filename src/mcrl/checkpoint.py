"""Checkpoints: plain .npz arrays plus JSON, never pickle, written atomically.

A checkpoint is a directory `checkpoints/step_<N>/` holding `state.npz` (every leaf of the train
state, keyed by its pytree path), `buffer.npz` (the replay buffer, optional) and `meta.json` (step
counters, the host RNG state, the config). It is written under a temporary name and renamed into place;
`checkpoints/latest` is then replaced atomically, so a kill at any moment leaves the previous checkpoint
usable. Loading uses `numpy.load(allow_pickle=False)`: it runs no code.
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

# The normaliser's histograms are derived from its ring buffer; they are rebuilt on load, not stored.
_DERIVED = ("c1", "c2", "c3")


def _flatten(tree) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    out = {}
    for path, leaf in leaves:
        key = jax.tree_util.keystr(path)
        if any(key.endswith(f".{d}") for d in _DERIVED):
            continue
        out[key] = np.asarray(leaf)
    return out


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


def save(run_dir: Path, step: int, state, meta: dict[str, Any], buffer_arrays: dict | None, keep: int) -> Path:
    ckpt_root = Path(run_dir) / "checkpoints"
    ckpt_root.mkdir(parents=True, exist_ok=True)
    final = ckpt_root / f"step_{step:09d}"
    tmp = ckpt_root / f".tmp-step_{step:09d}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    _write_npz(tmp / "state.npz", _flatten(jax.device_get(state)))
    if buffer_arrays is not None:
        _write_npz(tmp / "buffer.npz", buffer_arrays)
    (tmp / "meta.json").write_text(json.dumps({**meta, "step": step, "has_buffer": buffer_arrays is not None}))
    _fsync_dir(tmp)
    shutil.rmtree(final, ignore_errors=True)
    os.rename(tmp, final)
    latest_tmp = ckpt_root / ".latest.tmp"
    latest_tmp.write_text(final.name)
    os.replace(latest_tmp, ckpt_root / "latest")
    _fsync_dir(ckpt_root)
    for old in sorted(ckpt_root.glob("step_*"))[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def find(run_dir: Path, step: int | None = None) -> Path:
    """The newest complete checkpoint (or the one at `step`)."""
    ckpt_root = Path(run_dir) / "checkpoints"
    if step is not None:
        path = ckpt_root / f"step_{step:09d}"
        if not path.is_dir():
            have = sorted(p.name for p in ckpt_root.glob("step_*"))
            raise MCRLError(f"no checkpoint at step {step} in {run_dir}: available: {', '.join(have) or 'none'}")
        return path
    latest = ckpt_root / "latest"
    if not latest.is_file():
        raise MCRLError(f"{run_dir} has no checkpoint: train it (longer than checkpoint_every steps) first")
    return ckpt_root / latest.read_text().strip()


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
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    new_leaves = []
    for path, leaf in leaves:
        key = jax.tree_util.keystr(path)
        if any(key.endswith(f".{d}") for d in _DERIVED):
            new_leaves.append(leaf)
            continue
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


def load_buffer_arrays(ckpt: Path) -> dict[str, np.ndarray] | None:
    path = ckpt / "buffer.npz"
    return _load_npz(path) if path.is_file() else None
