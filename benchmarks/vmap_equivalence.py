"""Does a grid trained with `--backend vmap` learn like the same grid trained run by run (`--backend local`)?

    python benchmarks/vmap_equivalence.py VMAP_EXP LOCAL_EXP [--json out.json]

Both arguments are experiment directories of `mcrl sweep` over the same grid (same preset, alphas and seeds),
one per backend, e.g. (the check in docs/studies/vmap-whole-runs.md)::

    mcrl sweep --preset fetchreach-sacmc --alphas 0,0.2 --seeds 3 --backend vmap --exp EXP/vmap
    mcrl sweep --preset fetchreach-sacmc --alphas 0,0.2 --seeds 3 --backend local --exp EXP/local

Runs are not compared step for step (float reassociation makes their trajectories part;
docs/studies/vmap-whole-runs.md), but by outcome. Per run (matched by alpha and seed between the backends) the script reads the final evaluation's success and return and the area under the
evaluation curve (mean success over the evaluations during training, which separates fast from slow learners
even when every run ends at 1.0), and prints, per configuration and over all pairs, the mean of each backend and
the paired difference vmap - local with a 95% bootstrap interval over the pairs. An interval containing 0 means
no systematic difference was found at this number of pairs; its width says how large a difference could hide.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from _common import write_json
from mcrl.analysis.stats import bootstrap_ci
from mcrl.run.rundir import read_json, read_rows
from mcrl.renames import new_names

N_BOOT = 10_000


def read_runs(exp: Path) -> dict[tuple[float, int], dict[str, float]]:
    """(intrinsic_alpha, seed) -> {"success", "return", "auc"} for every finished run of an experiment directory."""
    out = {}
    for rd in sorted((exp / "runs").iterdir()):
        if not (rd / "done").exists():
            continue
        cfg, final = new_names(read_json(rd / "config.json")), read_json(rd / "final_eval.json")
        total = cfg["total_steps"]
        curve = [r["success_rate"] for r in read_rows(rd / "eval.csv")
                 if r["step"] < total and r.get("success_rate") is not None]
        out[(float(cfg["intrinsic_alpha"]), int(cfg["seed"]))] = {
            "success": final["success_rate"], "return": final["mean_return"],
            "auc": float(np.mean(curve)) if curve else float("nan")}
    return out


def paired_ci(diffs: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """Mean of the paired differences and its 95% percentile-bootstrap interval over the pairs."""
    lo, hi = bootstrap_ci(diffs, n_boot=N_BOOT, rng=seed)
    return float(diffs.mean()), lo, hi


def compare(vmap: dict, local: dict) -> dict:
    keys = sorted(set(vmap) & set(local))
    if not keys:
        raise SystemExit("error: the two experiments share no finished (alpha, seed) run: give sweeps of one grid")
    groups = {f"alpha={a:g}": [k for k in keys if k[0] == a] for a in sorted({k[0] for k in keys})}
    groups["all pairs"] = keys
    res = {"pairs": len(keys), "only_vmap": sorted(set(vmap) - set(local)),
           "only_local": sorted(set(local) - set(vmap)), "groups": {}}
    for name, ks in groups.items():
        res["groups"][name] = {}
        for m in ("success", "return", "auc"):
            v = np.array([vmap[k][m] for k in ks])
            loc = np.array([local[k][m] for k in ks])
            mean, lo, hi = paired_ci(v - loc)
            res["groups"][name][m] = {"n": len(ks), "vmap": float(v.mean()), "local": float(loc.mean()),
                                      "diff": mean, "ci": [lo, hi], "contains_0": bool(lo <= 0 <= hi)}
    res["runs"] = [{"alpha": k[0], "seed": k[1], "vmap": vmap[k], "local": local[k]} for k in keys]
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("vmap_exp", type=Path)
    p.add_argument("local_exp", type=Path)
    p.add_argument("--json", type=Path, help="also write the numbers here")
    args = p.parse_args(argv)
    for d in (args.vmap_exp, args.local_exp):
        if not (d / "runs").is_dir():
            print(f"error: {d} is not an experiment directory of `mcrl sweep` (no runs/)", file=sys.stderr)
            return 2
    res = compare(read_runs(args.vmap_exp), read_runs(args.local_exp))
    print(f"{res['pairs']} matched (alpha, seed) pairs"
          + (f"; unmatched: vmap {res['only_vmap']}, local {res['only_local']}"
             if res["only_vmap"] or res["only_local"] else ""))
    print("| runs | alpha | seed | final success vmap / local | final return vmap / local | curve AUC vmap / local |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in res["runs"]:
        v, loc = r["vmap"], r["local"]
        print(f"| pair | {r['alpha']:g} | {r['seed']} | {v['success']:.2f} / {loc['success']:.2f} | "
              f"{v['return']:.2f} / {loc['return']:.2f} | {v['auc']:.3f} / {loc['auc']:.3f} |")
    print()
    print("| configuration | pairs | measure | vmap mean | local mean | vmap - local [95% CI over pairs] |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, ms in res["groups"].items():
        for m, s in ms.items():
            print(f"| {name} | {s['n']} | {m} | {s['vmap']:.3f} | {s['local']:.3f} | "
                  f"{s['diff']:+.3f} [{s['ci'][0]:+.3f}, {s['ci'][1]:+.3f}] |")
    if args.json:
        write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
