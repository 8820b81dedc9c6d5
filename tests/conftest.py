import os
import shutil
import signal
import tempfile

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")

# One JAX compilation cache for the whole session: this process, its pytest-xdist workers (they inherit the
# environment) and every run a test starts in a subprocess (sweeps, kill-and-resume, chaos) load an executable an
# earlier process compiled for the same computation instead of compiling it again. Results are bit for bit the
# same (the resume tests compare a resumed run from one process with an uninterrupted one from another). A cached
# run of `mcrl train` at the plumbing tests' sizes took 7.9 s of CPU instead of 19.5 s. The directory is new for
# each session (`make test` on a fresh clone starts empty) and removed at its end; a JAX_COMPILATION_CACHE_DIR
# set by the caller is used and kept.
_OWN_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _OWN_CACHE = tempfile.mkdtemp(prefix="mcrl-tests-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWN_CACHE
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")  # CPU compiles here take < 1 s too
    # JAX writes an entry in place; with a size limit it takes a file lock around every read and write, so that no
    # process reads an entry another is still writing (filelock comes with Ray, a test dependency)
    import importlib.util

    if importlib.util.find_spec("filelock") is not None:
        os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(8 << 30))

# The fault tests play a user's Ctrl-C. A suite started as a background job (`cmd &` in a script) inherits SIGINT
# ignored and would pass that on to the runs it starts, which then rightly keep ignoring it (mcrl.run.stop).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import pytest  # noqa: E402

# Small networks for tests that check plumbing rather than learning; the learning test uses thesis sizes.
SMALL = {"hidden_sizes": [64, 64], "intrinsic_hidden_sizes": [64, 64], "buffer_size": 20_000, "batch_size": 64,
         "eval_episodes": 2, "learning_starts": 100}


@pytest.fixture
def small():
    return dict(SMALL)


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


# The longest files first (`make test` runs a file per worker, in collection order, with --no-loadscope-reorder:
# pytest-xdist otherwise hands out the files with the most tests first, which sent the one-test
# test_learning.py last and left the other worker idle for its 5 minutes). Ordered by their wall time in a
# 2-worker run on 2 cores (AMD EPYC Zen 4, 2026-11-29; test_schedule.py, added later, by its ~7 min alone on 2 busy
# cores); files not named keep their alphabetical order after these.
LONGEST_FIRST = ["test_intrinsic.py", "test_vmap.py", "test_learning.py", "test_schedule.py", "test_sweep.py",
                 "test_chaos.py", "test_losses.py",
                 "test_precision.py", "test_install.py", "test_decide.py", "test_report.py", "test_faults.py",
                 "test_gpu_script.py", "test_mc.py", "test_resume.py", "test_sac.py", "test_migrate.py",
                 "test_render.py"]


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's tests keep their order
