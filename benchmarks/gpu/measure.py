"""The GPU path, measured: is mcrl's CUDA path right, how fast is it, and how long would the thesis' tables take.

    python benchmarks/gpu/measure.py --out gpu.json [--budget-s 500]      # on the GPU machine (run.sh calls it)
    python benchmarks/gpu/measure.py --dry-run --out dry.json               # the same on the CPU at tiny sizes
    python benchmarks/gpu/measure.py --out gpu.json --only fetchpush_single  # equivalence + the phases named

Phases, each in child processes (`child.py`) stopped at its share of the budget, the JSON rewritten after each:

1. equivalence: a FetchPush SAC-MC run (`fetchpush-sacmc-0.2`, seed 0, thesis sizes) alone and as member 0 of
   a 2-run vmapped group on the default device (the GPU), and alone on the same machine's CPU
   (JAX_PLATFORMS=cpu, concurrently): the same jax, flax, MuJoCo and inputs, so any difference is the device's.
   Their metrics.csv are compared value by value at a stated tolerance. The child also checks that jax sees a
   GPU and that mcrl's float32 layers really multiply in float32 (not TF32).
2. throughput, with mcrl's own loop: (a) one `fetchpush-sacmc-0.2` run; (b) a vmapped group of 12 FetchPush
   runs (6 `fetchpush-sac`, 6 `fetchpush-sacmc-0.2`) with environment workers; (c) a vmapped group of 8 AntMaze
   runs at batch 2048 (4 `antmaze-sac`, 4 `antmaze-sacmc`). Compile time, steady-state steps/s and the cost of
   an evaluation episode come from the runs' log rows (`analyse.py`).
3. projections: the wall time of the FetchPush table (6 arms x 6 seeds, 150k steps) and the AntMaze table
   (3 arms x 4 seeds, 400k steps) from the measured group rates.

`--dry-run` runs the same phases with tiny networks, batches and groups on whatever device jax finds (the CPU
here; `tests/test_gpu_script.py`), the throughput phase (a) stopped by its budget as on the GPU.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import analyse
import procs

# Equivalence (benchmarks/gpu/README.md, "Equivalence"), rows logged every step, |x - y| <= atol + rtol * max(|x|, |y|):
# - first gradient step: the same initial state and batch, so only the device's float32 arithmetic differs;
#   tight, except what the percentile normaliser makes of it (its 24-bit histogram bins are 2**-16 relative
#   wide, and the first step's bounds are close together, so a bin crossed moves the MC reward by up to ~1e-3);
# - blocks: means over blocks of BLOCK steps of SAC's own columns over the few hundred steps: loose, as float
#   reassociation grows through training (on one CPU a vmapped run and the run alone differ by up to 2e-2 in
#   these after 300 gradient steps);
# - the MC models' columns after the first step diverge fastest (up to 0.8 relative between those two CPU runs):
#   reported, not judged.
NORMALISED = ("mean_mc_reward", "mean_intrinsic_reward", "mean_total_reward", "mc_bound_low", "mc_bound_high",
              "intrinsic_bound_low", "intrinsic_bound_high")  # both names: issue 52 renames the MC ones
SAC_COLUMNS = ("episodes", "train_return", "train_success_rate", "train_goal_moved", "eval_success_rate",
               "eval_mean_return", "actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean",
               "mean_ext_reward", "saturated_share", "logp_gap")
BLOCK = 50
CHECKS = {"first_step": (1e-4, 1e-6), "first_step_normalised": (1e-2, 1e-6), "blocks": (0.1, 1e-3)}
TOLERANCE = {"rule": "|x - y| <= atol + rtol * max(|x|, |y|)",
             **{k: {"rtol": r, "atol": a} for k, (r, a) in CHECKS.items()},
             "columns": {"first_step": "every metric but the normalised ones", "first_step_normalised":
                         list(NORMALISED), "blocks": list(SAC_COLUMNS)}, "block_steps": BLOCK,
             "reported_not_judged": "the MC models' and normaliser's columns after the first step"}


# The tables: runs that can share a vmapped group (`mcrl.run.group.group_key`), steps per run. FetchPush: 6 arms
# (SAC, SAC-MC alpha 0.2 ... 1.0) x 6 seeds differ only in alpha; AntMaze: antmaze-sac and antmaze-sacmc x 4 seeds
# share shapes, antmaze-sacmc-p94 (another max_percentile) x 4 forms its own.
FETCH_TABLE = ("fetchpush", [36], 150_000)
ANT_TABLE = ("antmaze", [8, 4], 400_000)


@dataclass(frozen=True)
class Phase:
    name: str
    runs: tuple[tuple[str, int], ...]  # (preset, how many seeds from 0)
    env_workers: int
    share: float  # of the measurement's budget
    steps: int | None = None  # a step cap (None: the preset's total_steps; the budget ends the phase)
    budget_s: float | None = None  # seconds of its own instead of its share


FULL = {"model": {}, "grace_s": procs.GRACE_S, "equivalence_steps": 400, "log_every": 100,
        "eval_every": {"fetchpush": 1000, "antmaze": 1000}, "equivalence_share": 0.24,
        "phases": [Phase("fetchpush_single", (("fetchpush-sacmc-0.2", 1),), 0, 0.11),
                   Phase("fetchpush_group", (("fetchpush-sac", 6), ("fetchpush-sacmc-0.2", 6)), 6, 0.28),
                   Phase("antmaze_group", (("antmaze-sac", 4), ("antmaze-sacmc", 4)), 4, 0.37)]}
TINY = {"model": {"hidden_sizes": [16], "mc_hidden_sizes": [16], "batch_size": 32, "buffer_size": 20_000},
        "antmaze_episode": 50, "grace_s": 3.0, "equivalence_steps": 150, "log_every": 50, "compile_cache": True,
        "eval_every": {"fetchpush": 150, "antmaze": 150}, "equivalence_share": 0.3,
        "phases": [Phase("fetchpush_single", (("fetchpush-sacmc-0.2", 1),), 0, 0.0, budget_s=10.0),
                   Phase("fetchpush_group", (("fetchpush-sac", 1), ("fetchpush-sacmc-0.2", 1)), 1, 0.35, 300),
                   Phase("antmaze_group", (("antmaze-sac", 1), ("antmaze-sacmc", 1)), 1, 0.35, 300)]}


def config(preset: str, seed: int, sizes: dict, **overrides):
    """The preset as the table runs it, with the measurement's logging (and, in a dry run, tiny sizes)."""
    from mcrl.config import resolve_config

    base = resolve_config(preset)
    over = {"seed": seed, "checkpoint_every": 10**9, "save_buffer": False, "video_every": 0, **sizes["model"]}
    if base.env_id.startswith("AntMaze") and "antmaze_episode" in sizes:
        over["env_kwargs"] = {**base.env_kwargs, "max_episode_steps": sizes["antmaze_episode"]}
    return resolve_config(preset, {**over, **overrides})


class Measurement:
    def __init__(self, out: Path, work: Path, budget_s: float, dry_run: bool, require_gpu: bool, extra: dict):
        self.out, self.work, self.dry_run, self.require_gpu = out, work, dry_run, require_gpu
        work.mkdir(parents=True, exist_ok=True)
        self.sizes = TINY if dry_run else FULL
        self.t0, self.budget_s = time.monotonic(), budget_s
        # a dry run's children share compilations (same shapes on the CPU) and compile without LLVM's optimisations,
        # for speed; a measurement must do neither
        flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()
        self.env = {"JAX_COMPILATION_CACHE_DIR": str(work / "jax-cache"),
                    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
                    "XLA_FLAGS": flags} if self.sizes.get("compile_cache") else {}
        self.doc: dict = {"schema": 1, "mode": "dry-run" if dry_run else "gpu", "budget_s": budget_s,
                          "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": procs.machine(),
                          "source": procs.source(), **extra, "phases": {}, "errors": []}
        self.save()

    def save(self) -> None:
        self.doc["wall_s"] = round(time.monotonic() - self.t0, 2)
        tmp = self.out.with_name(self.out.name + ".tmp")
        tmp.write_text(json.dumps(self.doc, indent=1, default=str))
        os.replace(tmp, self.out)

    def left(self) -> float:
        return self.budget_s - (time.monotonic() - self.t0)

    def alloc(self, share: float, later: float) -> float:
        """This phase's seconds: its share of what is left, in proportion to the shares still to come."""
        return max(self.left() * share / (share + later), 0.0)

    def _record(self, name: str, child: procs.Child) -> dict:
        res = child.result()
        info = res["info"]
        jobs = info.get("jobs", {})
        failed = [f"{name}/{j}: {v.get('error')}" for j, v in jobs.items() if v.get("status") == "failed"]
        if info.get("error"):
            failed.append(f"{name}: {info['error']}")
        elif not info:
            failed.append(f"{name}: the child wrote nothing (exit {res['rc']}); see log_tail")
        self.doc["errors"] += failed
        self.doc["phases"][name] = {k: v for k, v in res.items() if k != "info" and (k != "log_tail" or failed)}
        self.doc["phases"][name]["jobs"] = jobs
        return info

    # ---------------------------------------------------------------- phase 1
    def equivalence(self, later: float) -> bool:
        s = self.sizes
        over = {"total_steps": s["equivalence_steps"], "log_every": 1, "eval_every": 0, "final_eval_episodes": 2}
        mc, sac = config("fetchpush-sacmc-0.2", 0, s, **over), config("fetchpush-sac", 1, s, **over)
        d = self.work / "equivalence"
        jobs = [{"name": "single", "group": False, "configs": [mc.to_dict()], "dirs": [str(d / "dev-single")]},
                {"name": "group", "group": True, "configs": [mc.to_dict(), sac.to_dict()],
                 "dirs": [str(d / "dev-group-0"), str(d / "dev-group-1")]}]
        cpu_job = [{"name": "single", "group": False, "configs": [mc.to_dict()], "dirs": [str(d / "cpu-single")]}]
        budget = self.alloc(s["equivalence_share"], later)
        end = time.monotonic() + budget
        dev = procs.Child("equivalence_device", jobs, self.work, budget, self.env, s["grace_s"])
        cpu = None  # started once the device's single run is done: then it compiles beside the group, not the run
        while True:
            info, done = dev.info(), dev.poll()
            if info.get("error") or (self.require_gpu and info.get("backend") not in (None, "gpu")):
                for c in (dev, cpu):
                    c is not None and c.stop_now()
                break
            if cpu is None and "single" in info.get("jobs", {}):
                cpu = procs.Child("equivalence_cpu", cpu_job, self.work, end - time.monotonic(),
                                  {**self.env, "JAX_PLATFORMS": "cpu"}, s["grace_s"])
            if done and (cpu is None or cpu.poll()):
                break
            time.sleep(0.2)
        info = self._record("equivalence_device", dev)
        cpu_info = self._record("equivalence_cpu", cpu) if cpu is not None else {}
        self.doc.update(backend=info.get("backend"), devices=info.get("devices"), device_kind=info.get("device_kind"),
                        versions=info.get("versions"), matmul_check=info.get("matmul"),
                        cpu_reference_backend=cpu_info.get("backend"))
        self.doc["gpu_ok"] = info.get("backend") == "gpu"
        if self.require_gpu and not self.doc["gpu_ok"]:
            self.doc["errors"].append(f"jax.devices() is not a GPU: {info.get('devices')} ({info.get('error')})")
            return False
        from mcrl.run.rundir import LEARNING_COLUMNS, read_rows

        rows = {k: read_rows(d / k / "metrics.csv") for k in ("dev-single", "dev-group-0", "cpu-single")}
        metric = [c for c in LEARNING_COLUMNS if c != "step"]
        first = mc.learning_starts + 1
        eq = {"preset": "fetchpush-sacmc-0.2", "seed": 0, "steps": over["total_steps"], "gradient_steps":
              over["total_steps"] - mc.learning_starts, "tolerance": TOLERANCE}
        for name, other in (("device_single_vs_device_group", "dev-group-0"),
                            ("device_single_vs_cpu_single", "cpu-single")):
            a, b = rows["dev-single"], rows[other]
            blocks = [analyse.block_means(x, metric, mc.learning_starts, BLOCK) for x in (a, b)]
            at_first = [[r for r in x if r["step"] == first] for x in (a, b)]
            other_cols = [c for c in metric if c not in SAC_COLUMNS]
            res = {"first_step": analyse.compare(*at_first, *CHECKS["first_step"],
                                                 ["step", *[c for c in metric if c not in NORMALISED]]),
                   "first_step_normalised": analyse.compare(*at_first, *CHECKS["first_step_normalised"],
                                                            ["step", *NORMALISED]),
                   "blocks": analyse.compare(*blocks, *CHECKS["blocks"], ["step", *SAC_COLUMNS])}
            res["passed"] = all(res[k]["passed"] for k in CHECKS)
            reported = analyse.compare(*blocks, 0.0, 0.0, ["step", *other_cols])
            res["reported"] = {k: reported.get(k) for k in ("rows", "values", "max_rel", "worst", "bit_identical")}
            eq[name] = res
        eq["float32_matmul_ok"] = (info.get("matmul") or {}).get("mcrl_dense_float32", 1.0) < 1e-5
        eq["passed"] = all(eq[k]["passed"] for k in ("device_single_vs_device_group", "device_single_vs_cpu_single")) \
            and eq["float32_matmul_ok"]
        self.doc["equivalence"] = eq
        return True

    # ---------------------------------------------------------------- phase 2
    def throughput(self, phase: Phase, later: float) -> None:
        s = self.sizes
        cfgs, dirs = [], []
        for preset, n in phase.runs:
            for seed in range(n):
                family = "antmaze" if preset.startswith("antmaze") else "fetchpush"
                over = {"log_every": s["log_every"], "eval_every": s["eval_every"][family], "eval_episodes": 1,
                        "final_eval_episodes": 1}
                if phase.steps:
                    over["total_steps"] = phase.steps
                cfgs.append(config(preset, seed, s, **over))
                dirs.append(str(self.work / phase.name / f"{preset}-s{seed}"))
        job = {"name": phase.name, "group": len(cfgs) > 1, "configs": [c.to_dict() for c in cfgs], "dirs": dirs,
               "env_workers": phase.env_workers}
        budget = phase.budget_s or self.alloc(phase.share, later)
        child = procs.Child(phase.name, [job], self.work, budget, self.env, s["grace_s"])
        procs.wait_all([child])
        self._record(phase.name, child)
        from mcrl.run.rundir import read_rows

        figs = analyse.throughput(read_rows(Path(dirs[0]) / "metrics.csv"), read_rows(Path(dirs[0]) / "eval.csv"),
                                  cfgs[0].learning_starts, len(cfgs))
        c = cfgs[0]
        figs.update(presets=[f"{p} x{n}" for p, n in phase.runs], batch_size=c.batch_size,
                    hidden_sizes=list(c.hidden_sizes),
                    intrinsic_hidden_sizes=list(getattr(c, "intrinsic_hidden_sizes", None) or c.mc_hidden_sizes),
                    env_workers=phase.env_workers, budget_s=round(budget, 1), log_every=c.log_every,
                    eval_every=c.eval_every, matmul_precision=c.matmul_precision)
        self.doc.setdefault("throughput", {})[phase.name] = figs

    # ---------------------------------------------------------------- phase 3
    def projections(self) -> None:
        from mcrl.config import resolve_config

        tp = self.doc.get("throughput", {})
        out = {}
        for (name, sets, steps), phase, preset in ((FETCH_TABLE, "fetchpush_group", "fetchpush-sacmc-0.2"),
                                                     (ANT_TABLE, "antmaze_group", "antmaze-sacmc")):
            c, figs = resolve_config(preset), tp.get(phase, {})
            out[name] = analyse.project(name, sets, steps, c.eval_every, c.eval_episodes, c.n_final_eval_episodes,
                                        figs, figs.get("members", 0))
        single = tp.get("fetchpush_single", {}).get("steady_steps_per_s")
        out["fetchpush"]["one_run_at_a_time_train_h"] = None if not single else 36 * 150_000 / single / 3600
        self.doc["projections"] = out

    def run(self, only: set[str] | None = None) -> int:
        """All phases, or the equivalence check and the throughput phases named in `only` (a second, shorter
        window: the projections need every group, so they are left out)."""
        phases = [p for p in self.sizes["phases"] if only is None or p.name in only]
        shares = [p.share for p in phases]
        if not self.equivalence(sum(shares)):
            self.save()
            return 1
        self.save()
        for i, phase in enumerate(phases):
            self.throughput(phase, sum(shares[i + 1:]))
            self.save()
        if only is None:
            self.projections()
        self.save()
        return 0 if not self.doc["errors"] and self.doc["equivalence"]["passed"] else 1


def summary(doc: dict) -> str:
    lines = [f"{doc['mode']}: {doc['machine'].get('gpu') or doc['machine'].get('cpu')}, backend {doc.get('backend')}, "
             f"{doc['wall_s']:.0f} s"]
    eq = doc.get("equivalence", {})
    for k in ("device_single_vs_device_group", "device_single_vs_cpu_single"):
        if k in eq:
            lines.append(f"  {k}: passed={eq[k]['passed']} first step max_rel={eq[k]['first_step'].get('max_rel')}, "
                         f"SAC blocks max_rel={eq[k]['blocks'].get('max_rel')}, MC blocks max_rel="
                         f"{eq[k]['reported'].get('max_rel')}")
    for k, f in doc.get("throughput", {}).items():
        lines.append(f"  {k}: {f.get('steady_steps_per_s')} group steps/s x {f['members']} runs, "
                     f"compile {f.get('compile_s')} s, eval {f.get('eval_s_per_member_episode')} s/episode")
    for k, p in doc.get("projections", {}).items():
        lines.append(f"  {k} table: {p.get('total_h')} h ({p.get('train_h')} h training)")
    lines += [f"  error: {e}" for e in doc["errors"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="the JSON to write")
    p.add_argument("--budget-s", type=float, default=None, help="seconds for all phases (500; dry run 900)")
    p.add_argument("--dry-run", action="store_true", help="tiny sizes, any device")
    p.add_argument("--work", help="where the runs go (default: a temporary folder)")
    p.add_argument("--extra", help="a JSON file merged into the output (run.sh's install record)")
    p.add_argument("--only", help="comma-separated throughput phases to run after the equivalence check "
                   "(fetchpush_single, fetchpush_group, antmaze_group); default: all, with projections")
    a = p.parse_args(argv)
    names = {ph.name for ph in FULL["phases"]}
    only = None if not a.only else set(a.only.split(","))
    if only is not None and not only <= names:
        p.error(f"unknown phase in --only: {sorted(only - names)}; choose from {sorted(names)}")
    extra = json.loads(Path(a.extra).read_text()) if a.extra else {}
    # a dry run's phases end by their step caps (but for the single run's budget stop); its budget only bounds a
    # machine so loaded that they do not, so it is generous: the test suite runs beside other work
    budget = a.budget_s or (900.0 if a.dry_run else 500.0)
    work = Path(a.work or tempfile.mkdtemp(prefix="mcrl-gpu-"))
    m = Measurement(Path(a.out).absolute(), work, budget, a.dry_run, not a.dry_run, extra)
    try:
        rc = m.run(only)
    except Exception as e:  # still leave the JSON
        import traceback

        m.doc["errors"].append(f"measure.py: {type(e).__name__}: {e}")
        m.doc["traceback"] = traceback.format_exc()
        rc = 2
    m.save()
    print(summary(m.doc), flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
