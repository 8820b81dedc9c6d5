"""A package a command needs but the install lacks: one line naming the install command, exit 2, nothing written."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mcrl.cli import main
from mcrl.errors import MCRLError
from mcrl.extras import require, require_installed


def _run(args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, set[Path]]:
    before = set(tmp_path.rglob("*"))
    rc = main(args)
    err = capsys.readouterr().err.strip()
    return rc, err, set(tmp_path.rglob("*")) - before


def test_require_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    assert require("json", "sweep", "x") is json
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ModuleNotFoundError
    for check in (require, require_installed):
        with pytest.raises(MCRLError) as e:
            check("ray", "sweep", "mcrl sweep --backend ray")
        assert str(e.value) == ("mcrl sweep --backend ray needs the optional package 'ray': "
                                'install it with pip install "mcrl[sweep]"')
    monkeypatch.setitem(sys.modules, "scipy", None)
    with pytest.raises(MCRLError, match=r"reinstall mcrl \(pip install mcrl\)"):
        require("scipy", None, "mcrl report")


@pytest.mark.parametrize("module,flags,needle", [
    ("ray", ["--backend", "ray"], "mcrl sweep --backend ray needs the optional package 'ray'"),
    ("mlflow", ["--tracking"], "mcrl sweep --tracking needs the optional package 'mlflow'"),
    ("mlflow", ["--tracking-uri", "http://localhost:5000"], "needs the optional package 'mlflow'"),
])
def test_sweep_without_its_extra(module: str, flags: list[str], needle: str, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, module, None)
    monkeypatch.chdir(tmp_path)  # the default experiment directory would be under the working directory
    rc, err, new = _run(["sweep", "--preset", "fetchreach-sacmc", "--alphas", "0", "--seeds", "1", "--steps", "100",
                         "--exp", str(tmp_path / "exp"), "--no-progress", *flags], tmp_path, capsys)
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("mcrl: error: ") and needle in err, err
    assert 'pip install "mcrl[sweep]"' in err
    assert not new


def test_report_with_a_broken_main_dependency(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "sweep.json").write_text(json.dumps({"preset": "x", "runs": [{"name": "r", "config_key": "k", "seed": 0}]}))
    monkeypatch.setitem(sys.modules, "rliable", None)
    rc, err, new = _run(["report", str(exp)], tmp_path, capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "'rliable'" in err and "pip install mcrl" in err, err
    assert not new
