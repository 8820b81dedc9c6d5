"""Packages a command needs but a plain ``pip install mcrl`` may lack.

A missing package must end in mcrl's one-line error (``mcrl: error: ...``, exit code 2) naming
what to install, never in a traceback from deep inside a command. The CLI checks a command's
packages before the command starts, so nothing is written when one is missing.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from mcrl.errors import MCRLError

# The packages of each command beyond training (see pyproject.toml), checked before it runs.
PLOT_MODULES = ("matplotlib",)
REPORT_MODULES = ("matplotlib", "scipy", "rliable")
RENDER_MODULES = ("matplotlib", "PIL", "imageio")


def _error(module: str, extra: str | None, feature: str, why: str = "") -> MCRLError:
    if extra is None:  # a main dependency: only a broken install lacks it
        return MCRLError(f"{feature} needs the package {module!r}, which `pip install mcrl` installs, but it does "
                         f"not import{f' ({why})' if why else ''}: reinstall mcrl (pip install mcrl)")
    return MCRLError(f"{feature} needs the optional package {module!r}: install it with "
                     f'pip install "mcrl[{extra}]"')


def require(module: str, extra: str | None, feature: str) -> ModuleType:
    """Import ``module`` for ``feature``; raise MCRLError naming the install command when it is missing.

    ``extra`` is the optional-dependency group of pyproject.toml that provides the module (e.g.
    ``"sweep"``), or None for a package of the main dependencies.
    """
    try:
        return importlib.import_module(module)
    except ImportError as e:  # ModuleNotFoundError, or a package whose own dependencies are missing
        why = f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0]}"
        raise _error(module, extra, feature, why) from None


def require_installed(module: str, extra: str | None, feature: str) -> None:
    """Like :func:`require`, but only look the top-level package up, without importing it.

    For packages whose import has effects that must come later: Ray reads its authentication
    settings from the environment when it is first imported, and ``mcrl sweep`` sets them first.
    """
    try:
        found = importlib.util.find_spec(module) is not None  # None also for a None entry in sys.modules
    except ValueError:  # already imported, without a __spec__
        found = True
    except ImportError:
        found = False
    if not found:
        raise _error(module, extra, feature)


def require_all(modules: tuple[str, ...], extra: str | None, feature: str) -> None:
    """:func:`require` each of ``modules``; the first missing one raises."""
    for m in modules:
        require(m, extra, feature)
