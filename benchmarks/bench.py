"""Speed benchmark: mcrl against stable-baselines3 (SAC+HER on FetchPush at the thesis' settings) and against
the machine's float32 matmul roofline.

    python benchmarks/bench.py [--steps N] [--repeats R] [--skip-sb3] [--skip-mcrl] [--torch-threads N]
                               [--json out.json]        # or: make bench

Prints one Markdown table (progress goes to stderr); ``--json`` writes every number and a description of the
system. What each column measures, and how, is in docs/performance.md ("How bench.py measures").
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from _common import cpuinfo, log, md_head, md_row, usable_cores, write_json

#: mcrl presets benchmarked, in table order.
MCRL_PRESETS = ("fetchpush-sac", "fetchpush-sacmc-0.2")

#: The thesis' FetchPush settings for SB3 SAC+HER (Appendix A of the thesis).
SB3_SAC_KWARGS: dict[str, Any] = dict(
    learning_rate=3e-4,
    buffer_size=1_000_000,
    learning_starts=1000,
    batch_size=256,
    tau=0.005,
    gamma=0.99,
    train_freq=1,
    gradient_steps=1,
    policy_kwargs=dict(net_arch=[256, 256, 256]),
)
SB3_HER_KWARGS: dict[str, Any] = dict(n_sampled_goal=4, goal_selection_strategy="future")


# --------------------------------------------------------------------------------------------
# 1. Roofline
# --------------------------------------------------------------------------------------------

#: (rows, n): x of shape (rows, n) times w of shape (n, n).
ROOFLINE_SHAPES: tuple[tuple[int, int], ...] = (
    (256, 256),
    (256, 512),
    (256, 1024),
    (512, 512),
    (1024, 1024),
    (2048, 2048),
)


def _matmul_chain(k: int):
    """Jitted ``(x, w) -> x @ w @ w ... @ w`` (``k`` products, a loop XLA cannot fold)."""
    import jax

    @jax.jit
    def chain(x, w):
        return jax.lax.fori_loop(0, k, lambda _, y: y @ w, x)

    return chain


def roofline_gflops(
    shapes: tuple[tuple[int, int], ...] = ROOFLINE_SHAPES,
    repeats: int = 7,
    min_time_s: float = 0.25,
    flop_per_call: float = 0.5e9,
) -> dict:
    """Best sustained float32 matmul GFLOP/s of JAX on this machine.

    For every ``(rows, n)`` in ``shapes`` a jitted function chains ``k`` products
    ``x <- x @ w`` (x: rows x n, w: n x n orthogonal), with ``k`` chosen so that one call does
    about ``flop_per_call`` FLOPs. Each of ``repeats`` repetitions times back-to-back calls
    for at least ``min_time_s``; the median over repetitions is that shape's figure.

    Returns ``{"gflops": best median, "best_shape": "RxN@NxN", "shapes": {shape: {...}}}``.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    rng = np.random.default_rng(0)
    per_shape: dict[str, dict] = {}
    for rows, n in shapes:
        flop_per_mm = 2.0 * rows * n * n
        k = max(1, round(flop_per_call / flop_per_mm))
        w_np, _ = np.linalg.qr(rng.standard_normal((n, n)))
        w = jnp.asarray(w_np, dtype=jnp.float32)
        x = jnp.asarray(rng.standard_normal((rows, n)), dtype=jnp.float32)

        chain = _matmul_chain(k)

        chain(x, w).block_until_ready()  # compile
        for _ in range(2):  # warm caches and thread pool
            chain(x, w).block_until_ready()

        rates = []
        for _ in range(repeats):
            calls = 0
            y = x
            t0 = time.perf_counter()
            while True:
                y = chain(y, w)
                calls += 1
                if calls % 4 == 0:
                    y.block_until_ready()
                    elapsed = time.perf_counter() - t0
                    if elapsed >= min_time_s:
                        break
            rates.append(calls * k * flop_per_mm / elapsed / 1e9)
        name = f"{rows}x{n}@{n}x{n}"
        per_shape[name] = {
            "gflops_median": statistics.median(rates),
            "gflops_all": rates,
            "matmuls_per_call": k,
        }
        log(f"roofline {name:>20}: {per_shape[name]['gflops_median']:8.1f} GFLOP/s")

    best = max(per_shape, key=lambda s: per_shape[s]["gflops_median"])
    return {
        "gflops": per_shape[best]["gflops_median"],
        "best_shape": best,
        "shapes": per_shape,
        "repeats": repeats,
        "min_time_s": min_time_s,
        "jax_devices": [str(d) for d in jax.devices()],
    }


# --------------------------------------------------------------------------------------------
# 2. stable-baselines3 SAC+HER
# --------------------------------------------------------------------------------------------


def _make_timed_sac_class():
    """SAC subclass that logs the start time and duration of each rollout step, and the
    duration of each ``train`` call and of the replay sampling inside it."""
    from stable_baselines3 import SAC

    class TimedSAC(SAC):
        def _setup_model(self) -> None:
            super()._setup_model()
            # (num_timesteps before the call, perf_counter at its start, duration)
            self.rollout_log: list[tuple[int, float, float]] = []
            # (num_timesteps after the rollout step, train() duration, replay-sampling part)
            self.train_log: list[tuple[int, float, float]] = []
            self._sample_s = 0.0
            sample = self.replay_buffer.sample

            def timed_sample(*args, **kwargs):
                t0 = time.perf_counter()
                out = sample(*args, **kwargs)
                self._sample_s += time.perf_counter() - t0
                return out

            self.replay_buffer.sample = timed_sample

        def collect_rollouts(self, *args, **kwargs):
            n, t0 = self.num_timesteps, time.perf_counter()
            out = super().collect_rollouts(*args, **kwargs)
            self.rollout_log.append((n, t0, time.perf_counter() - t0))
            return out

        def train(self, gradient_steps: int, batch_size: int = 64) -> None:
            self._sample_s = 0.0
            t0 = time.perf_counter()
            super().train(gradient_steps, batch_size)
            self.train_log.append((self.num_timesteps, time.perf_counter() - t0, self._sample_s))

    return TimedSAC


def _window_stats(model, lo: int, hi: int) -> dict:
    """Speed of the training loop between env steps ``lo`` and ``hi`` (needs step ``hi`` to
    have been started, so that the window's wall time is closed)."""
    starts = {n: t0 for n, t0, _ in model.rollout_log}
    wall = starts[hi] - starts[lo]
    rollout = sum(d for n, _, d in model.rollout_log if lo <= n < hi)
    # train() runs after the rollout step that took num_timesteps from n-1 to n.
    train = [(d, sample) for n, d, sample in model.train_log if lo < n <= hi]
    train_s = sum(d for d, _ in train)
    sample_s = sum(sample for _, sample in train)
    return {
        "steps_per_s": (hi - lo) / wall,
        "ms_per_env_step": 1e3 * rollout / (hi - lo),
        "ms_per_grad_step": 1e3 * (train_s - sample_s) / len(train),
        "ms_per_replay_sample": 1e3 * sample_s / len(train),
        "grad_steps": len(train),
    }


def _probe_torch_threads(model, candidates: list[int], max_calls: int, max_s: float) -> dict:
    """Median ms of one SB3 gradient step (``model.train``) for each torch thread count.

    Each candidate gets two untimed calls, then up to ``max_calls`` timed ones or ``max_s``
    seconds, whichever ends first (two threads on a busy 2-core machine can be 50x slower,
    so the probe must not run a fixed number of steps). The extra updates only happen during
    warm-up, so they do not affect the timed windows.
    """
    import torch

    batch_size = SB3_SAC_KWARGS["batch_size"]
    result = {}
    for threads in candidates:
        torch.set_num_threads(threads)
        times: list[float] = []
        t_start = time.perf_counter()
        for i in range(max_calls + 2):
            t0 = time.perf_counter()
            model.train(gradient_steps=1, batch_size=batch_size)
            if i >= 2:
                times.append(time.perf_counter() - t0)
            if time.perf_counter() - t_start > max_s:
                break
        result[threads] = 1e3 * statistics.median(times) if times else math.inf
    return result


def sb3_steps_per_s(
    steps: int,
    repeats: int,
    warmup_grad_steps: int = 300,
    torch_threads: int | None = None,
    env_id: str = "FetchPush-v4",
    seed: int = 0,
) -> dict:
    """Training-loop speed of SB3 SAC+HER at the thesis' settings (docs/performance.md, "How bench.py measures").

    Runs ``learning_starts`` (1000) random steps and ``warmup_grad_steps`` untimed learning
    steps. With ``torch_threads=None`` it then times a few gradient steps with each candidate
    thread count (1 and the number of usable cores) and keeps the fastest; otherwise it uses
    ``torch_threads``. Then the same run continues for ``repeats`` timed windows of ``steps``
    env steps (one gradient step each). Returns medians over the windows plus the per-window
    values, the probe results and the settings used.
    """
    import gymnasium as gym
    import gymnasium_robotics
    import stable_baselines3
    import torch
    from stable_baselines3 import HerReplayBuffer
    from torch.utils.flop_counter import FlopCounterMode

    gym.register_envs(gymnasium_robotics)
    previous_threads = torch.get_num_threads()
    candidates = sorted({1, usable_cores()}) if torch_threads is None else [torch_threads]
    try:
        torch.set_num_threads(candidates[0])
        env = gym.make(env_id)
        model = _make_timed_sac_class()(
            "MultiInputPolicy",
            env,
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs=dict(SB3_HER_KWARGS),
            device="cpu",
            seed=seed,
            verbose=0,
            **SB3_SAC_KWARGS,
        )
        start = SB3_SAC_KWARGS["learning_starts"] + warmup_grad_steps
        log(
            f"sb3: {SB3_SAC_KWARGS['learning_starts']} random + {warmup_grad_steps} warm-up "
            f"learning steps, torch thread candidates {candidates}, "
            f"then {repeats} x {steps} timed steps"
        )
        t_learn = time.perf_counter()
        model.learn(total_timesteps=start)

        probe: dict[int, float] = {}
        if len(candidates) > 1:
            probe = _probe_torch_threads(model, candidates, max_calls=40, max_s=3.0)
            log("sb3 thread probe (ms/grad step): "
                 + ", ".join(f"{t} thread(s) {v:.1f}" for t, v in probe.items()))
        threads = min(probe, key=probe.get) if probe else candidates[0]
        torch.set_num_threads(threads)

        # Timed part: the same training loop, continued. The +1 starts one more step, whose
        # start time closes the last window.
        bounds = [start + i * steps for i in range(repeats + 1)]
        model.learn(total_timesteps=bounds[-1] + 1, reset_num_timesteps=False)
        learn_s = time.perf_counter() - t_learn
        windows = []
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            windows.append(_window_stats(model, lo, hi))
            log(
                f"sb3 window ({threads} thread(s)): {windows[-1]['steps_per_s']:.1f} steps/s, "
                f"{windows[-1]['ms_per_grad_step']:.2f} ms/grad, "
                f"{windows[-1]['ms_per_replay_sample']:.2f} ms/replay sample, "
                f"{windows[-1]['ms_per_env_step']:.2f} ms/env"
            )

        # Matmul FLOPs of one gradient step (an extra update after timing; harmless).
        with FlopCounterMode(display=False) as counter:
            model.train(gradient_steps=1, batch_size=SB3_SAC_KWARGS["batch_size"])
        grad_step_gflop = counter.get_total_flops() / 1e9
        env.close()
    finally:
        torch.set_num_threads(previous_threads)

    def med(key: str) -> float:
        return statistics.median(w[key] for w in windows)

    return {
        "steps_per_s": med("steps_per_s"),
        "ms_per_grad_step": med("ms_per_grad_step"),
        "ms_per_env_step": med("ms_per_env_step"),
        "ms_per_replay_sample": med("ms_per_replay_sample"),
        "grad_step_gflop": grad_step_gflop,
        "torch_threads": threads,
        "thread_probe_ms_per_grad_step": probe,
        "windows": windows,
        "learn_wall_s": learn_s,
        "settings": {
            "env_id": env_id,
            "steps": steps,
            "repeats": repeats,
            "warmup_grad_steps": warmup_grad_steps,
            "seed": seed,
            "sac": SB3_SAC_KWARGS,
            "her": SB3_HER_KWARGS,
            "torch": torch.__version__,
            "stable_baselines3": stable_baselines3.__version__,
        },
    }


# --------------------------------------------------------------------------------------------
# 3. mcrl
# --------------------------------------------------------------------------------------------


def mcrl_numbers(preset: str, steps: int, repeats: int) -> dict:
    """mcrl's own training-loop numbers for ``preset``.

    Returns a dict with the medians ``steps_per_s``, ``ms_per_grad_step``, ``ms_per_env_step``
    and ``grad_step_gflop``. Raises ImportError when mcrl (or its benchmarking module) is
    missing; the caller reports that as "mcrl: not available".
    """
    from harness import measure_training

    return measure_training(preset=preset, steps=steps, repeats=repeats)


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def system_info() -> dict:
    """Hardware and software versions, for the JSON report and the table's caption."""
    info = cpuinfo()
    cpu = info.get("model name") or platform.processor() or "unknown"
    flags = set(info.get("flags", "").split())
    versions = {}
    for mod in ("jax", "jaxlib", "flax", "optax", "numpy", "gymnasium", "gymnasium_robotics",
                "mujoco", "torch", "stable_baselines3"):
        try:
            versions[mod] = __import__(mod).__version__
        except Exception:  # not installed, or no __version__
            versions[mod] = None
    return {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable_cores(),
        "simd": sorted(f for f in flags if f in {"avx2", "fma", "avx512f", "amx_tile"}),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "loadavg_1_5_15min": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "XLA_FLAGS", "JAX_PLATFORMS")},
        "versions": versions,
    }


def _derive(row: dict, roofline: float | None, sb3_steps_per_s: float | None) -> dict:
    """Add achieved GFLOP/s, roofline time and ratios to a measured row (in place)."""
    gflop, ms = row.get("grad_step_gflop"), row.get("ms_per_grad_step")
    if gflop and ms:
        row["achieved_gflops"] = gflop / (ms / 1e3)
        if roofline:
            row["roofline_ms_per_grad_step"] = 1e3 * gflop / roofline
            row["vs_roofline"] = row["achieved_gflops"] / roofline
    if sb3_steps_per_s and row.get("steps_per_s"):
        row["vs_sb3"] = row["steps_per_s"] / sb3_steps_per_s
    return row


def _fmt(x: Any, spec: str) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return format(x, spec)


def _fmt_load(load: Any) -> str:
    return "/".join(f"{x:.1f}" for x in load) if load else "—"


def markdown_table(report: dict) -> str:
    """The report as a Markdown table (one row per system) with a short caption."""
    sysinfo, roof = report["system"], report.get("roofline") or {}
    roof_g = roof.get("gflops")
    head = (
        f"CPU: {sysinfo['cpu']} ({sysinfo['cpus_usable']} usable cores, "
        f"{', '.join(sysinfo['simd']) or 'no AVX2'}); roofline {_fmt(roof_g, '.1f')} GFLOP/s "
        f"(JAX float32 matmul, best shape {roof.get('best_shape', '—')}); "
        f"{report['steps']} steps x {report['repeats']} windows, medians; load average "
        f"{_fmt_load(report.get('loadavg_at_start'))} at start, "
        f"{_fmt_load(sysinfo.get('loadavg_1_5_15min'))} at end (1/5/15 min; above the core "
        f"count means other work shared the CPU)."
    )
    cols = ["system", "steps/s", "ms/grad step", "ms/env step", "GFLOP/grad step",
            "GFLOP/s achieved", "roofline ms/grad step", "% of roofline", "mcrl/SB3"]
    lines = [head, "", *md_head(cols)]
    for row in report["rows"]:
        if row.get("status") != "ok":
            cells = [row["system"], row.get("status", "—")] + ["—"] * (len(cols) - 2)
        else:
            cells = [
                row["system"],
                _fmt(row.get("steps_per_s"), ".1f"),
                _fmt(row.get("ms_per_grad_step"), ".2f"),
                _fmt(row.get("ms_per_env_step"), ".2f"),
                _fmt(row.get("grad_step_gflop"), ".3f"),
                _fmt(row.get("achieved_gflops"), ".1f"),
                _fmt(row.get("roofline_ms_per_grad_step"), ".2f"),
                _fmt(row.get("vs_roofline"), ".1%"),
                _fmt(row.get("vs_sb3"), ".2f"),
            ]
        lines.append(md_row(cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=1000, help="env steps per timed window")
    p.add_argument("--repeats", type=int, default=3, help="timed windows (median reported)")
    p.add_argument("--skip-sb3", action="store_true", help="do not run the SB3 baseline")
    p.add_argument("--skip-mcrl", action="store_true", help="do not run mcrl's presets")
    p.add_argument("--json", type=Path, help="write the full report to this JSON file")
    p.add_argument("--torch-threads", type=int, default=None,
                   help="torch.set_num_threads for SB3 (default: probe 1 and all cores, "
                        "keep the faster)")
    p.add_argument("--sb3-warmup-grad-steps", type=int, default=300,
                   help="untimed SB3 learning steps after learning_starts")
    p.add_argument("--roofline-repeats", type=int, default=7)
    args = p.parse_args(argv)

    report: dict[str, Any] = {
        "steps": args.steps,
        "repeats": args.repeats,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "loadavg_at_start": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "rows": [],
    }
    failed = False

    log("== roofline")
    report["roofline"] = roofline_gflops(repeats=args.roofline_repeats)

    sb3_row: dict[str, Any] = {"system": "SB3 SAC+HER (torch)"}
    if args.skip_sb3:
        sb3_row["status"] = "skipped"
    else:
        log("== stable-baselines3")
        try:
            sb3 = sb3_steps_per_s(args.steps, args.repeats, args.sb3_warmup_grad_steps,
                                  args.torch_threads)
            sb3_row.update(sb3, status="ok")
            sb3_row["system"] = f"SB3 SAC+HER (torch {sb3['torch_threads']} thread(s))"
        except ImportError as e:
            sb3_row["status"] = f"sb3: not available ({e.name or e})"
            log(sb3_row["status"])
        except Exception as e:  # keep going: the other parts are still worth reporting
            failed = True
            sb3_row.update(status=f"error: {type(e).__name__}", error=traceback.format_exc())
            log(sb3_row["error"])
    report["rows"].append(sb3_row)

    for preset in MCRL_PRESETS:
        row: dict[str, Any] = {"system": f"mcrl {preset}"}
        if args.skip_mcrl:
            row["status"] = "skipped"
        else:
            log(f"== mcrl {preset}")
            try:
                row.update(mcrl_numbers(preset, args.steps, args.repeats), status="ok")
            except ImportError as e:
                row["status"] = "mcrl: not available"
                row["error"] = repr(e)
                log(f"mcrl: not available ({e!r})")
            except Exception as e:
                failed = True
                row.update(status=f"error: {type(e).__name__}", error=traceback.format_exc())
                log(row["error"])
        report["rows"].append(row)

    roof_g = report["roofline"]["gflops"]
    sb3_sps = sb3_row.get("steps_per_s") if sb3_row.get("status") == "ok" else None
    for row in report["rows"]:
        if row.get("status") == "ok":
            _derive(row, roof_g, None if row is sb3_row else sb3_sps)
    # Versions last: torch/sb3/mcrl are imported by now if they are installed.
    report["system"] = system_info()

    print(markdown_table(report))
    if args.json:
        write_json(args.json, report, default=str)
        log(f"wrote {args.json}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
