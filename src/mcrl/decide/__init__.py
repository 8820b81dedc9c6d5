"""Confirmatory experiments that stop when they are decided: ``mcrl decide PLAN``.

A sequential plan (``plan.yaml``) fixes the arms, fresh seeds, batches, claims, level, spending and futility rule
before any data; ``mcrl decide`` runs one batch at a time through a sweep backend and takes a look after each, with
group-sequential bounds, until every claim is reproduced, futile or not reproduced at the maximum.

- ``boundaries``: Lan-DeMets spending and the Armitage-McPherson-Rowe recursion (bounds, crossing probabilities).
- ``plan``: the plan file, validated, and its hash.
- ``look``: one look, pure: the tie-corrected rank-sum z, each claim's bounds at its level in force, decisions.
- ``runner``: batches through `mcrl.sweep`, ``looks.jsonl``, the lock, the pinned commit; ``mcrl decide``.
- ``report``: the report section of a sequential experiment.
"""
from mcrl.decide.look import take_look
from mcrl.decide.plan import Plan, load_plan

__all__ = ["Plan", "load_plan", "take_look"]
