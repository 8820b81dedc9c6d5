"""The package layout stays readable: no import cycles (module level or inside functions), no huge modules,
and the run directory's readers import no JAX."""
import ast
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
MAX_LINES = 400  # issue 27: no module over 400 lines


def _modules() -> dict[str, Path]:
    out = {}
    for p in (SRC / "mcrl").rglob("*.py"):
        parts = p.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


def _imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """mcrl modules that `name` imports anywhere in its file (functions included)."""
    pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found |= {f"{base}.{a.name}" for a in node.names}
    return {m for m in found if m in modules and m != name}


def test_no_import_cycles():
    modules = _modules()
    graph = {m: _imports(p, m, modules) for m, p in modules.items()}
    # a package's __init__ is imported by its submodules' import machinery anyway; a submodule importing its own
    # package's __init__ that imports it back is a cycle too, so no edge is dropped
    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n, stack + [n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles


def test_the_training_loop_does_not_import_the_video_package():
    """video/ renders runs (it imports run/); the loop gets its video step passed in, so no arrow goes back up."""
    modules = _modules()
    up = {m: sorted(n for n in _imports(p, m, modules) if n.split(".")[:2] == ["mcrl", "video"])
          for m, p in modules.items() if m.startswith("mcrl.run")}
    assert not any(up.values()), up


def test_no_module_is_huge():
    big = {m: n for m, p in _modules().items() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not big, big


def test_run_directory_readers_and_analysis_import_no_jax():
    code = ("import sys, mcrl.run.rundir, mcrl.analysis.report, mcrl.analysis.plots, mcrl.analysis.stats; "
            "print('jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
