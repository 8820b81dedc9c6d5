"""Installing mcrl fits into an existing environment (issue 28, item 5).

pyproject.toml states compatible ranges; the exact tested set lives in constraints.txt, which `make` and CI
install with `pip install -c constraints.txt`. The slow test installs the repository, with no constraints, into
a fresh virtual environment that already holds other (compatible) numpy and matplotlib versions, and checks that
pip keeps them and that a tiny real training then runs.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]
CONSTRAINTS = REPO / "constraints.txt"
LOWEST = REPO / "constraints-lowest.txt"  # the lower bounds, installed and tested together

# What a researcher's environment already holds: released versions other than constraints.txt's, inside the
# ranges of pyproject.toml (test_install_versions_differ_from_the_tested_set checks both).
THEIR_NUMPY = "2.3.5"
THEIR_MATPLOTLIB = "3.10.9"


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _requirements() -> list[Requirement]:
    """Every requirement of pyproject.toml: the dependencies and all optional extras (mcrl itself left out)."""
    project = _pyproject()["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in project.get("optional-dependencies", {}).values():
        reqs += [Requirement(r) for r in extra]
    return [r for r in reqs if canonicalize_name(r.name) != "mcrl"]


def _constraints(path: Path = CONSTRAINTS) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        m = re.fullmatch(r"([A-Za-z0-9_.\-]+)==([^\s;]+)", line)
        assert m, f"{path.name}: {line!r} is not an exact 'name==version' pin"
        pins[canonicalize_name(m.group(1))] = m.group(2)
    return pins


def _spec(name: str):
    specs = [r.specifier for r in _requirements() if canonicalize_name(r.name) == canonicalize_name(name)]
    assert specs, f"{name} is not a requirement in pyproject.toml"
    return specs[0]


def test_pyproject_states_ranges_not_pins():
    pinned = [str(r) for r in _requirements() if any(s.operator in ("==", "===") for s in r.specifier)]
    assert not pinned, f"exact pins belong in constraints.txt, not pyproject.toml: {pinned}"
    unbounded = [str(r) for r in _requirements() if not any(s.operator == ">=" for s in r.specifier)]
    assert not unbounded, f"give these a tested lower bound (>=): {unbounded}"


def test_constraints_pin_every_requirement_inside_its_range():
    pins = _constraints()
    for req in _requirements():
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is required by pyproject.toml but not pinned in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), (
            f"constraints.txt pins {req.name}=={pins[name]}, outside pyproject.toml's range {req}")


def test_lower_bounds_are_the_tested_lowest_set():
    lowest = _constraints(LOWEST)
    for req in _requirements():
        if "cuda12" in req.extras:
            continue  # no CUDA machine to test on (see pyproject.toml)
        lower = [s.version for s in req.specifier if s.operator == ">="]
        assert lowest.get(canonicalize_name(req.name)) == lower[0], (
            f"{req}: its lower bound must be the version tested in {LOWEST.name} "
            f"(which has {lowest.get(canonicalize_name(req.name))})")


def test_requires_python_admits_the_tested_python():
    from packaging.specifiers import SpecifierSet

    spec = SpecifierSet(_pyproject()["project"]["requires-python"])
    assert spec.contains("3.11.7") and spec.contains("3.12.1")
    assert spec.contains(".".join(map(str, sys.version_info[:3])))


def test_mujoco_that_breaks_gymnasium_robotics_is_excluded():
    """mujoco 3.12.0 and newer (4.0.0 too) break gymnasium-robotics 1.4.2 (AssertionError in set_joint_qpos on
    reset); 3.11.0 works."""
    assert not _spec("mujoco").contains("3.12.0") and not _spec("mujoco").contains("4.0.0")
    assert _spec("mujoco").contains("3.11.0")
    assert _spec("mujoco").contains(_constraints()["mujoco"])


def test_makefile_installs_with_constraints_and_reinstalls_when_they_change(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("no make")
    for f in ("Makefile", "pyproject.toml", "constraints.txt"):
        shutil.copy(REPO / f, tmp_path / f)
    dry = subprocess.run(["make", "-n", "--always-make", "install"], cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout
    installs = [ln for ln in dry.splitlines() if re.search(r"pip install .*-e ", ln)]
    assert installs and all("-c constraints.txt" in ln for ln in installs), dry

    stamp = tmp_path / ".venv" / ".installed"
    stamp.parent.mkdir()
    stamp.touch()
    os.utime(tmp_path / "pyproject.toml", (1_000_000, 1_000_000))
    os.utime(tmp_path / "constraints.txt", (1_000_000, 1_000_000))
    up_to_date = subprocess.run(["make", "-q", ".venv/.installed"], cwd=tmp_path)
    assert up_to_date.returncode == 0
    (tmp_path / "constraints.txt").touch()  # a newer constraints.txt than the install
    stale = subprocess.run(["make", "-q", ".venv/.installed"], cwd=tmp_path)
    assert stale.returncode == 1, "make does not reinstall when constraints.txt changes"


def test_the_version_is_the_installed_one_and_the_changelog_says_what_changed():
    """pyproject.toml, `mcrl.__version__` and the installed metadata (which provenance.json records) name one
    version, the changelog's newest section is that version's, and it is 0.2.0 or later: 0.2.0 is the first
    version that refuses the files 0.1 wrote (Config.from_run_json, checkpoint.py), so a version that went back
    would let files of two formats carry one number."""
    from importlib.metadata import version as installed

    import mcrl

    version = _pyproject()["project"]["version"]
    assert mcrl.__version__ == version, f"mcrl.__version__ {mcrl.__version__} != pyproject.toml's {version}"
    assert installed("mcrl") == version, (f"the installed metadata says {installed('mcrl')}, pyproject.toml "
                                          f"{version}: reinstall (`make install`)")
    assert Version(version) >= Version("0.2.0")
    sections = re.findall(r"^## \[?(\d+\.\d+\.\d+)\]? - \d{4}-\d{2}-\d{2}$", (REPO / "CHANGELOG.md").read_text(),
                          re.M)
    assert sections and sections[0] == version, f"CHANGELOG.md's newest section is {sections[:1]}, not {version}"


def test_install_versions_differ_from_the_tested_set():
    """The slow test's premise: its numpy/matplotlib are compatible, and not the ones pip would pick itself."""
    pins = _constraints()
    for name, theirs in (("numpy", THEIR_NUMPY), ("matplotlib", THEIR_MATPLOTLIB)):
        assert Version(theirs) != Version(pins[name])
        assert _spec(name).contains(theirs), f"{name} {theirs} is outside pyproject.toml's range {_spec(name)}"


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n" \
                                 f"{proc.stderr[-3000:]}"
    return proc


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_pip_install_keeps_existing_numpy_and_matplotlib(tmp_path):
    # A copy of the working tree, so that pip's in-tree build leaves nothing in the repository.
    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "runs", "experiments", "build", "*.egg-info", "__pycache__", ".pytest_cache"))
    env = {k: v for k, v in os.environ.items()
           if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME", "PIP_CONSTRAINT", "PIP_REQUIREMENT")
           and not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}  # a user's, not the suite's
    env["MUJOCO_GL"] = env.get("MUJOCO_GL", "egl")
    venv = tmp_path / "env"
    # A fresh environment (no --system-site-packages) with the researcher's own numpy and matplotlib.
    _run([sys.executable, "-m", "venv", str(venv)], env=env)
    py = venv / "bin" / "python"
    pip = [str(py), "-m", "pip", "--disable-pip-version-check", "install", "-q"]
    _run(pip + [f"numpy=={THEIR_NUMPY}", f"matplotlib=={THEIR_MATPLOTLIB}"], env=env)

    _run(pip + [str(src)], env=env)  # no constraints: pyproject.toml's ranges alone

    versions = _run([str(py), "-c", "import numpy, matplotlib, mcrl; print(numpy.__version__, matplotlib.__version__)"],
                    env=env, cwd=tmp_path).stdout.split()
    assert versions == [THEIR_NUMPY, THEIR_MATPLOTLIB], f"pip replaced the environment's numpy/matplotlib: {versions}"
    _run([str(py), "-m", "pip", "check"], env=env)

    run_dir = tmp_path / "run"
    _run([str(venv / "bin" / "mcrl"), "train", "--env", "FetchReach-v4", "--steps", "300",
          "--set", "learning_starts=100", "--set", "eval_every=0", "--run-dir", str(run_dir)], env=env, cwd=tmp_path)
    with open(run_dir / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert int(rows[-1]["step"]) == 300
    assert math.isfinite(float(rows[-1]["critic_loss"]))  # gradient steps ran and gave a finite loss
    final = json.loads((run_dir / "final_eval.json").read_text())
    assert final["step"] == 300 and final["episodes"] > 0 and 0.0 <= final["success_rate"] <= 1.0
