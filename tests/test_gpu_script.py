"""The prepared GPU measurement (benchmarks/gpu/, issue 51) runs here as a dry run: the same phases, child
processes, budget stop, equivalence checks, figures and projections as on a GPU machine, at tiny sizes on the CPU.
The analysis is also checked on rows made up here."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

GPU = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu"
sys.path.insert(0, str(GPU))
import analyse  # noqa: E402


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu-dry-run")
    proc = subprocess.run(["bash", str(GPU / "run.sh"), "dry-run", str(out)], capture_output=True, text=True,
                          env={**os.environ, "PY": sys.executable}, timeout=1200)
    doc = json.loads((out / "gpu-dry-run.json").read_text())
    return proc, doc


@pytest.mark.slow
def test_dry_run_writes_every_key(dry_run):
    proc, doc = dry_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert doc["errors"] == [] and doc["mode"] == "dry-run" and doc["backend"] == "cpu"
    for key in ("machine", "source", "versions", "devices", "matmul_check", "equivalence", "throughput",
                "projections", "phases", "wall_s", "budget_s"):
        assert key in doc, key
    assert doc["source"]["src_sha256"] and doc["machine"]["cores"] >= 1
    for dist in ("jax", "jaxlib", "flax", "optax", "numpy", "mujoco", "gymnasium", "gymnasium-robotics"):
        assert doc["versions"][dist], dist
    assert set(doc["phases"]) == {"equivalence_device", "equivalence_cpu", "fetchpush_single", "fetchpush_group",
                                  "antmaze_group"}
    assert all(p["cpu_s"] is not None for p in doc["phases"].values())


@pytest.mark.slow
def test_dry_run_equivalence_is_computed_and_passes(dry_run):
    _, doc = dry_run
    eq = doc["equivalence"]
    assert eq["passed"] and eq["float32_matmul_ok"] and doc["matmul_check"]["mcrl_dense_float32"] < 1e-5
    assert set(eq["tolerance"]) >= {"first_step", "first_step_normalised", "blocks", "rule"}
    for name in ("device_single_vs_device_group", "device_single_vs_cpu_single"):
        res = eq[name]
        assert res["passed"]
        assert res["first_step"]["rows"] == 1 and res["first_step"]["values"] >= 10
        assert res["blocks"]["rows"] >= 1 and res["blocks"]["values"] > 0
        assert res["reported"]["values"] > 0
    # on the CPU the device and the CPU reference are the same computation
    assert eq["device_single_vs_cpu_single"]["blocks"]["bit_identical"]


@pytest.mark.slow
def test_dry_run_throughput_and_projections_come_from_the_measured_rows(dry_run):
    _, doc = dry_run
    single = doc["phases"]["fetchpush_single"]
    assert single["stopped_by_budget"] and single["jobs"]["fetchpush_single"]["status"] == "stopped"
    tp = doc["throughput"]
    # its figures depend on how far it got in 10 s (this machine's load): each is there, or said to be missing
    one = tp["fetchpush_single"]
    assert one["steady_steps_per_s"] is None or one["steady_steps_per_s"] > 0
    assert one["steady_steps_per_s"] is not None or one["missing"]
    for name, members in (("fetchpush_group", 2), ("antmaze_group", 2)):
        f = tp[name]
        assert f["members"] == members and f["missing"] == [], (name, f)
        assert f["steady_steps_per_s"] > 0 and f["run_steps_per_s"] == pytest.approx(members * f["steady_steps_per_s"])
        assert f["compile_s"] >= 0 and f["eval_s_per_member_episode"] > 0
    for table, phase, runs, steps in (("fetchpush", "fetchpush_group", 36, 150_000),
                                      ("antmaze", "antmaze_group", 12, 400_000)):
        p, f = doc["projections"][table], tp[phase]
        assert p["runs"] == runs == sum(p["groups"]) and max(p["groups"]) <= f["members"]
        assert p["train_h"] == pytest.approx(len(p["groups"]) * steps / f["steady_steps_per_s"] / 3600)
        assert p["compile_h"] == pytest.approx(len(p["groups"]) * f["compile_s"] / 3600)
        assert p["eval_h"] == pytest.approx(runs * p["eval_episodes_per_run"] * f["eval_s_per_member_episode"] / 3600)
        assert p["total_h"] == pytest.approx(p["train_h"] + p["compile_h"] + p["eval_h"])


def _rows(times: dict[int, float]) -> list[dict]:
    return [{"step": s, "time_s": t} for s, t in sorted(times.items())]


def test_throughput_reads_compile_steady_rate_and_evaluations_off_the_rows():
    # 100 random steps in 0.5 s; then the first learning interval takes 2 s of compilation on top of 1 s of steps;
    # 100 steps a second after that, and the evaluations at 300 and 500 add 3 s and 1 s (2 members x 1 episode)
    rows = _rows({100: 0.5, 200: 3.5, 300: 7.5, 400: 8.5, 500: 10.5, 600: 11.5})
    evals = [{"step": 300, "episodes": 1}, {"step": 500, "episodes": 1}]
    f = analyse.throughput(rows, evals, learning_starts=100, members=2)
    assert f["steady_steps_per_s"] == pytest.approx(100.0) and f["run_steps_per_s"] == pytest.approx(200.0)
    assert f["compile_s"] == pytest.approx(2.0) and f["first_eval_s"] == pytest.approx(3.0)
    assert f["eval_s_per_member_episode"] == pytest.approx(0.5) and f["missing"] == []
    short = analyse.throughput(rows[:3], evals[:1], learning_starts=100, members=2)
    assert short["steady_steps_per_s"] is None and short["compile_s"] is None and len(short["missing"]) == 3


def test_compare_and_block_means():
    a = [{"step": s, "x": float(s), "y": None} for s in range(101, 201)]
    b = [{**r, "x": r["x"] * (1 + 1e-3)} for r in a]
    blocks = analyse.block_means(a, ["x", "y"], 100, 50)
    assert [r["step"] for r in blocks] == [150, 200] and blocks[0]["x"] == pytest.approx(125.5)
    assert blocks[0]["y"] is None
    assert analyse.compare(a, b, 2e-3, 0.0, ["step", "x"])["passed"]
    worse = analyse.compare(a, b, 1e-4, 0.0, ["step", "x"])
    assert not worse["passed"] and worse["max_rel"] == pytest.approx(1e-3, rel=1e-3)
    assert not analyse.compare(a, b[:-1], 1.0, 1.0)["passed"]  # different log steps


def test_projection_splits_sets_into_measured_groups():
    figs = {"steady_steps_per_s": 100.0, "compile_s": 36.0, "eval_s_per_member_episode": 0.5}
    p = analyse.project("antmaze", [8, 4], 400_000, 10_000, 10, 100, figs, measured=8)
    assert p["groups"] == [8, 4] and p["eval_episodes_per_run"] == 39 * 10 + 100
    assert p["train_h"] == pytest.approx(2 * 4000 / 3600) and p["compile_h"] == pytest.approx(72 / 3600)
    assert p["eval_h"] == pytest.approx(12 * 490 * 0.5 / 3600)
    assert analyse.project("fetchpush", [36], 150_000, 5000, 10, 100, figs, measured=12)["groups"] == [12, 12, 12]
    none = analyse.project("x", [4], 10, 5, 1, 1, {"steady_steps_per_s": None}, measured=4)
    assert none["total_h"] is None and none["train_h"] is None


def test_only_runs_the_check_then_the_named_phases_and_shares_their_budget(tmp_path, monkeypatch):
    import measure

    m = measure.Measurement(tmp_path / "gpu.json", tmp_path / "work", 100.0, True, False, {})
    calls: list = []
    monkeypatch.setattr(m, "equivalence", lambda later: calls.append(("equivalence", later)) or
                        m.doc.__setitem__("equivalence", {"passed": True}) or True)
    monkeypatch.setattr(m, "throughput", lambda phase, later: calls.append((phase.name, later)))
    monkeypatch.setattr(m, "projections", lambda: calls.append(("projections", None)))
    assert m.run({"antmaze_group"}) == 0
    ant = next(p for p in measure.TINY["phases"] if p.name == "antmaze_group")
    # the equivalence check is shared against the named phase only, and no projection needs the missing groups
    assert calls == [("equivalence", ant.share), ("antmaze_group", 0)]
    calls.clear()
    assert m.run() == 0
    assert [c[0] for c in calls] == ["equivalence", *(p.name for p in measure.TINY["phases"]), "projections"]


def test_only_rejects_an_unknown_phase_before_anything_runs(tmp_path, capsys):
    import measure

    with pytest.raises(SystemExit) as e:
        measure.main(["--out", str(tmp_path / "gpu.json"), "--only", "fetchpush_single,antmaze"])
    assert e.value.code == 2 and "unknown phase in --only: ['antmaze']" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
