"""One process of the GPU measurement (`measure.py` starts it): imports jax on the device it is given, says what
it found, then trains its jobs with mcrl's own loop, a single run (`mcrl.run.trainer.train`, what `mcrl train`
runs) or a vmapped group (`mcrl.run.group.train_group`, what a `--backend vmap` sweep's worker runs).

    python child.py SPEC.json

SPEC: {"info": path, "jobs": [{"name", "group", "configs": [Config dicts], "dirs": [...], "env_workers"}]}.
The info file is written as soon as jax is up (devices, versions, a float32 matmul check) and again after each
job (its status and wall time), so a parent that stops this process at its time budget (SIGTERM: mcrl saves at
the episode's end and stops; then SIGKILL) still knows what happened; the figures come from the runs' files.
"""
from __future__ import annotations

import importlib.metadata as md
import json
import os
import sys
import time
import traceback
from pathlib import Path

T0 = time.monotonic()
DISTS = ("jax", "jaxlib", "jax-cuda13-plugin", "jax-cuda12-plugin", "flax", "optax", "numpy", "mujoco", "gymnasium",
         "gymnasium-robotics", "tensorboardX", "pettingzoo")


def _write(path: str, info: dict) -> None:
    tmp = Path(path + ".tmp")
    tmp.write_text(json.dumps(info, indent=1, default=str))
    os.replace(tmp, path)


def versions() -> dict[str, str | None]:
    """Installed versions of the packages the measurement depends on (None: not installed)."""
    out: dict[str, str | None] = {}
    for d in DISTS:
        try:
            out[d] = md.version(d)
        except md.PackageNotFoundError:
            out[d] = None
    return out


def matmul_check() -> dict[str, float]:
    """Largest relative error of a 512x512x512 matmul against float64: mcrl's float32 Dense layer (should be ~1e-7,
    true float32) and a plain `jnp.dot` at JAX's default precision (TF32 on an NVIDIA GPU: ~1e-3)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mcrl.algo.networks import Stack

    x = jax.random.normal(jax.random.PRNGKey(0), (512, 512))
    net = Stack((512,), (None,), "flax", "float32")  # flax init: zero bias, so the layer is x @ kernel
    params = net.init(jax.random.PRNGKey(1), x)["params"]
    kernel = np.asarray(params["Dense_0"]["kernel"], np.float64)
    ref = np.asarray(x, np.float64) @ kernel

    def rel(y) -> float:
        return float(np.abs(np.asarray(y, np.float64) - ref).max() / np.abs(ref).max())

    return {"mcrl_dense_float32": rel(jax.jit(net.apply)({"params": params}, x)),
            "jax_default_dot": rel(jax.jit(jnp.dot)(x, params["Dense_0"]["kernel"]))}


def main(spec_path: str) -> int:
    spec = json.loads(Path(spec_path).read_text())
    info: dict = {"pid": os.getpid(), "jax_platforms": os.environ.get("JAX_PLATFORMS"), "versions": versions(),
                  "jobs": {}}
    try:
        import jax

        import mcrl
        from mcrl.config import Config
        from mcrl.run import stop
        from mcrl.run.group import train_group
        from mcrl.run.trainer import train

        devices = jax.devices()
        info.update(backend=jax.default_backend(), devices=[str(d) for d in devices],
                    device_kind=devices[0].device_kind, mcrl_file=mcrl.__file__, matmul=matmul_check())
        import gymnasium
        import mujoco

        info["versions"].update(mujoco_module=mujoco.__version__, gymnasium_module=gymnasium.__version__)
    except Exception as e:  # a missing wheel, no device: the parent reports it
        info.update(error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc())
        _write(spec["info"], info)
        return 3
    info["ready_s"] = time.monotonic() - T0
    _write(spec["info"], info)
    rc = 0
    for job in spec["jobs"]:
        cfgs = [Config.from_dict(c) for c in job["configs"]]
        t = time.monotonic()
        try:
            if job["group"]:
                train_group(cfgs, job["dirs"], env_workers=job.get("env_workers", 0))
            else:
                train(cfgs[0], job["dirs"][0], progress=False)
            status: dict = {"status": "finished"}
        except stop.Stopped as e:
            status, rc = {"status": "stopped", "signal": e.signum}, e.exit_code
        except Exception as e:
            status, rc = {"status": "failed", "error": f"{type(e).__name__}: {e}",
                          "traceback": traceback.format_exc()}, 1
        info["jobs"][job["name"]] = {**status, "wall_s": time.monotonic() - t}
        _write(spec["info"], info)
        if status["status"] != "finished":
            break
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
