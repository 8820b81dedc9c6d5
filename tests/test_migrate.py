"""scripts/migrate_checkpoint.py: checkpoints written by commit 83e6d8d and by mcrl 0.1 become today's and
resume to exactly the numbers the original checkpoint resumes to."""
import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mcrl.config import resolve_config
from mcrl.errors import MCRLError
from mcrl.renames import old_name
from mcrl.run import checkpoint
from mcrl.run.rundir import LEARNING_COLUMNS, read_rows
from mcrl.run.trainer import resume, train

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "migrate_checkpoint.py"
# today's state.npz key prefixes -> the flat names of 83e6d8d's (and 0.1's) TrainState fields
OLD_NAMES = {".q_target": ".critic_target", ".q.opt": ".critic_opt", ".q.params": ".critic", ".pi.opt": ".actor_opt",
             ".pi.params": ".actor", ".ent.opt": ".ent_opt", ".ent.params": ".log_ent_coef",
             ".intrinsic.opt": ".mc_opt", ".intrinsic.params": ".mc"}


def _script():
    spec = importlib.util.spec_from_file_location("migrate_checkpoint", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _old_key(key: str) -> str:
    for new in sorted(OLD_NAMES, key=len, reverse=True):
        if key == new or key.startswith(new + "[") or key.startswith(new + "."):
            return OLD_NAMES[new] + key[len(new):]
    return key


def _run_to_resume(tmp_path, small, **over):
    """A finished run, and two copies of it that stop at its step-200 checkpoint (to be resumed)."""
    cfg = resolve_config("fetchreach-sacmc", {**small, "total_steps": 300, "checkpoint_every": 100,
                                              "keep_checkpoints": 5, "eval_every": 150, "log_every": 50, **over})
    orig = train(cfg, tmp_path / "orig", progress=False)
    copies = []
    for name in ("today", "old"):
        d = tmp_path / name
        shutil.copytree(orig, d)
        for p in (d / "checkpoints").glob("step_*"):
            if p.name != "step_000000200":
                shutil.rmtree(p)
        (d / "checkpoints" / "latest").write_text("step_000000200")
        for f in ("done", "final_eval.json"):
            (d / f).unlink()
        copies.append(d)
    return copies


def _assert_resume_alike(today, old):
    resume(today, progress=False)
    resume(old, progress=False)
    rows = lambda d: [{k: r[k] for k in LEARNING_COLUMNS} for r in read_rows(d / "metrics.csv")]  # noqa: E731
    assert rows(old) == rows(today) and len(rows(today)) == 6
    assert (old / "eval.csv").read_text() == (today / "eval.csv").read_text()
    a, b = checkpoint.find(today), checkpoint.find(old)
    assert a.name == b.name == "step_000000300"
    for f in ("state.npz", "normaliser.npz", "buffer.npz"):
        with np.load(a / f) as x, np.load(b / f) as y:
            assert sorted(x.files) == sorted(y.files), f
            for k in x.files:
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"{f} {k}")


@pytest.mark.slow
def test_a_83e6d8d_checkpoint_migrates_and_resumes_exactly(tmp_path, small):
    today, old = _run_to_resume(tmp_path, small)
    ck = old / "checkpoints" / "step_000000200"
    with np.load(ck / "state.npz") as f:
        arrays = {_old_key(k): f[k] for k in f.files}
    assert ".actor_opt[0].count" in arrays and ".log_ent_coef" in arrays and ".critic_target" in {
        k.split("[")[0] for k in arrays}
    np.savez(ck / "state.npz", **arrays)
    with pytest.raises(MCRLError, match="migrate_checkpoint"):
        resume(old, progress=False)
    mod = _script()
    assert mod.migrate(ck, ck) == ck
    assert json.loads((ck / "meta.json").read_text())["migrated_from"] == "83e6d8d"
    _assert_resume_alike(today, old)


@pytest.mark.slow
def test_an_mcrl_0_1_run_migrates_and_resumes_exactly(tmp_path, small):
    """0.1: the normaliser's window inside state.npz, config.json without `init` and `mc_history` in KL values;
    the run directory is converted in place by the command line."""
    today, old = _run_to_resume(tmp_path, small, init="flax", mc_history=3)  # a window of 3 x 64 values
    ck = old / "checkpoints" / "step_000000200"
    with np.load(ck / "state.npz") as f:
        arrays = {_old_key(k): f[k] for k in f.files}
    with np.load(ck / "normaliser.npz") as f:
        ring, ptr, count = f["ring"], f["ptr"], f["count"]
    assert int(count) == ring.size == 192 and 0 < int(ptr) < 192  # a full window that wrapped around
    keys = (ring.view(np.uint32) >> 8).astype(np.int64)
    c3 = np.bincount(keys, minlength=1 << 23).astype(np.int32)
    arrays.update({".norm.ring": ring, ".norm.ptr": ptr, ".norm.count": count, ".norm.c1":
                   c3.reshape(-1, 65536).sum(1), ".norm.c2": c3.reshape(-1, 256).sum(1), ".norm.c3": c3})
    np.savez(ck / "state.npz", **arrays)
    (ck / "normaliser.npz").unlink()
    for path in (old / "config.json", ck / "meta.json"):
        d = json.loads(path.read_text())
        cfg = d.get("config", d)
        old_names = {old_name(k): v for k, v in cfg.items()}  # 0.1 wrote the keys under their old names
        cfg.clear()
        cfg.update(old_names)
        del cfg["init"]
        cfg["mc_history"] = 192
        path.write_text(json.dumps(d))
    with pytest.raises(MCRLError, match="migrate_checkpoint"):
        resume(old, progress=False)
    assert _script().main([str(old)]) == 0
    assert json.loads((ck / "meta.json").read_text())["migrated_from"] == "0.1"
    assert json.loads((old / "config.json").read_text())["intrinsic_history"] == 3  # today's name
    _assert_resume_alike(today, old)


def test_a_todays_checkpoint_is_left_as_it_is(tmp_path, small):
    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 150, "eval_every": 0})
    ck = checkpoint.find(train(cfg, tmp_path / "r", progress=False))
    out = _script().migrate(ck, tmp_path / "copy")
    assert "migrated_from" not in json.loads((out / "meta.json").read_text())
    with np.load(ck / "state.npz") as x, np.load(out / "state.npz") as y:
        assert x.files == y.files
