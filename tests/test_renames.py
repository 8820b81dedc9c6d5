"""Issue 66, item 1: one mapping of old names to today's (`mcrl.renames`), applied where files are read; mcrl writes
only today's names, and the committed runs, written under the old ones, still read and regenerate their report."""
from __future__ import annotations

import io
import json
import tokenize
from pathlib import Path

import pytest

from mcrl.errors import MCRLError
from mcrl.renames import OLD_NAMES, new_names, new_path, old_name

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "mcrl"


def test_no_code_but_the_mapping_names_an_old_key():
    """`grep -rn mc_alpha src/mcrl` finds only the mapping, and no code outside it uses any old name as a string
    or an attribute (docstrings may tell the history)."""
    offenders = []
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "renames.py":
            continue
        text = path.read_text()
        if "mc_alpha" in text:
            offenders.append(f"{path.relative_to(ROOT)}: mc_alpha")
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            word = tok.string.strip("'\"") if tok.type == tokenize.STRING else tok.string
            if tok.type in (tokenize.NAME, tokenize.STRING) and word in OLD_NAMES:
                offenders.append(f"{path.relative_to(ROOT)}:{tok.start[0]}: {tok.string}")
    assert offenders == []


def test_old_names_read_as_todays_and_a_disagreement_is_refused():
    assert list(new_names({"seed": 1, "mc_alpha": 0.2, "mean_mc_reward": -0.5})) == [
        "seed", "intrinsic_alpha", "mean_intrinsic_reward"]
    assert new_names({"mc_alpha": 0.2, "intrinsic_alpha": 0.2}) == {"intrinsic_alpha": 0.2}  # the same value: one
    with pytest.raises(MCRLError, match="mc_alpha=0.2 and intrinsic_alpha=0.4 disagree.*give only intrinsic_alpha"):
        new_names({"mc_alpha": 0.2, "intrinsic_alpha": 0.4})
    assert new_path(".mc_models.params['MLP_0']['Dense_0']['kernel']") == ".intrinsic.params['MLP_0']['Dense_0']['kernel']"
    assert new_path(".metric_sums['mean_mc_reward']") == ".metric_sums['mean_intrinsic_reward']"
    assert new_path(".pi.params['MLP_0']['Dense_0']['bias']") == ".pi.params['MLP_0']['Dense_0']['bias']"
    assert old_name("intrinsic_lr") == "mc_lr" and old_name("intrinsic_schedule") == "intrinsic_schedule"


def test_a_sweep_json_from_before_the_renames_merges_under_todays_names():
    """A committed experiment's sweep.json (grid and set under old names) joined by a sweep given with today's
    names: one key each, today's, holding both sweeps' values."""
    from mcrl.sweep.experiment import merged_grid_and_set
    from mcrl.sweep.plan import build_plan

    old = {"grid": {"mc_alpha": [0.0, 0.2], "seed": [0]}, "set": {"total_steps": 1000, "mc_lr": 0.001}}
    plan = build_plan("fetchreach-sacmc", {"intrinsic_alpha": [0.4], "seed": [0]},
                      {"total_steps": 1000, "intrinsic_lr": 0.001})
    grid, fixed = merged_grid_and_set(old, plan)
    assert grid == {"intrinsic_alpha": [0.0, 0.2, 0.4], "seed": [0]}
    assert fixed == {"total_steps": 1000, "intrinsic_lr": 0.001}
    assert [r.name for r in plan.runs] == ["a0.4-s0"] and plan.runs[0].entry()["overrides"] == {
        "total_steps": 1000, "intrinsic_lr": 0.001, "intrinsic_alpha": 0.4, "seed": 0}


def test_a_committed_report_regenerates_unchanged(tmp_path, monkeypatch):
    """docs/antmaze/wiring: runs trained at a commit that wrote the old names (config.json and sweep.json
    `mc_alpha`, metrics.csv `mean_mc_reward`, `mc_bound_*`) regenerate the committed report.md byte for byte."""
    from mcrl.cli import main

    exp = ROOT / "docs" / "antmaze" / "wiring"
    run = exp / "runs" / "a0.2-s0"
    assert "mc_alpha" in json.loads((run / "config.json").read_text())
    assert "mean_mc_reward" in (run / "metrics.csv").read_text().split("\n")[0]
    monkeypatch.chdir(ROOT)  # the report names directories as given: relative to the repository, as committed
    assert main(["report", "docs/antmaze/wiring", "--out", str(tmp_path / "report")]) == 0
    made = (tmp_path / "report" / "report.md").read_text()
    assert made == (exp / "report" / "report.md").read_text()
    assert "| configuration | intrinsic_alpha |" in made and "mc_alpha" not in made
