"""Region scores (dicrl_torch.region) of finished runs' learned sets, from their config and
rows alone: no training, no rollouts (docs/design.md §6.1). Continuous games and the grid
(whose rows also get the obstacle and move scores).

    .venv/bin/python experiments/studies/region_scores.py docs/mpe_runs/seed0 [RUN_DIR ...]

RUN_DIR holds a run's ``results.json`` (its ``config`` rebuilds the task: the same
demonstrations, test set and bases). Prints one JSON line per learned row: the method,
the learner, its learned set's region scores and its bound (``region_recall_bound``).
Runs from before the region scores (the committed cell-basis runs) get them this way.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: common.py
from common import build_task  # noqa: E402


def scores(run: Path) -> list[dict]:
    """One record per learned row of ``run``'s ``results.json``."""
    res = json.loads((run / "results.json").read_text())
    cfg = OmegaConf.create(res["config"])
    task = build_task(cfg)
    if task.region_test() is None:
        raise SystemExit(f"{run}: the game has no region truth (region_truth() is None).")
    bounds = task.expressivity()
    out = []
    for name, method in res["methods"].items():
        for v, row in enumerate(method["learners"]):
            if row.get("constraints") is None:
                continue
            bound = bounds[-1] if len(method["learners"]) == 1 else bounds[v]
            mask = task.learned_mask(row)
            # the grid's recall over the obstacles its demonstrations make required
            required = task.required_rates(mask) if hasattr(task, "required_rates") else {}
            out.append({"run": str(run), "seed": cfg.seed, "method": name, "learner": v + 1,
                        **task.region_rates(mask), **required,
                        "region_recall_bound": bound, "SR": row.get("SR"),
                        "CR": row.get("CR_mean"), "CVR": row.get("CVR"),
                        "n_learned": row.get("n_learned")})
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for run in args.runs:
        for record in scores(run):
            print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
