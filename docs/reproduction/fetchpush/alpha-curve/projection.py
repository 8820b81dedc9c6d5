"""What more seeds would decide among the claims against mcrl's SAC on FetchPush (where issue 50's extension stopped).

Prints, for each way of adding seeds, the share of simulated futures in which each claim of the family "against mcrl
SAC" (docs/claims.yaml) would be reproduced, and refuted, at family-wise 0.05 (Holm over the whole family, as `mcrl
report` decides it). A future adds seeds to an arm by drawing finals, with replacement, from that arm's
committed final success rates: it assumes the seeds to come look like the seeds so far, which is all the data says
(and, drawing only values already seen, it understates how much new seeds can vary). The other arms keep their
committed finals.

    .venv/bin/python docs/reproduction/fetchpush/alpha-curve/projection.py [--sims 2000]

Deterministic given --seed. Reads only the committed small files (final_eval.json of each run).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mcrl.analysis.claims import NOT_REPRODUCED, REPRODUCED, claim_test, decide
from mcrl.analysis.registry import ArmRuns, load_registry

DOCS = Path(__file__).resolve().parents[3]
SCENARIOS = [  # (label, {arm name: seeds it has after the top-up}); the baseline is "mcrl SAC"
    ("as committed", {}),
    ("SAC-MC 0.8 and 1.0 at 12 seeds", {"SAC-MC 0.8": 12, "SAC-MC 1.0": 12}),
    ("mcrl SAC at 18 seeds", {"mcrl SAC": 18}),
    ("mcrl SAC at 24 seeds", {"mcrl SAC": 24}),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sims", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    reg = load_registry(DOCS / "claims.yaml")
    family = next(f for f in reg.families if f.baseline.name == "mcrl SAC")
    runs = ArmRuns()
    finals = {a.name: np.array([r.final[0] for r in runs.runs(a)])
              for a in (family.baseline, *(c.x for c in family.claims))}
    print("committed seeds: " + ", ".join(f"{k} {v.size}" for k, v in finals.items()))
    rng = np.random.default_rng(args.seed)
    for label, top_up in SCENARIOS:
        sims = 1 if not top_up else args.sims
        verdicts = np.empty((sims, len(family.claims)), object)
        for s in range(sims):
            drawn = {k: np.concatenate([v, rng.choice(v, max(0, top_up.get(k, 0) - v.size))])
                     for k, v in finals.items()}
            tests = [claim_test(drawn[c.x.name], drawn[family.baseline.name], c.by, c.kind) for c in family.claims]
            verdicts[s] = [v.verdict for v in decide(tests)]
        print(f"\n{label}: share of futures in which each claim is reproduced / refuted ({sims} simulated)")
        for c, v in zip(family.claims, verdicts.T):
            print(f"  {c.id:45s} {np.mean(v == REPRODUCED):.2f} / {np.mean(v == NOT_REPRODUCED):.2f}")


if __name__ == "__main__":
    main()
