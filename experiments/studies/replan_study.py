"""Study: a finished drone run's planned rows flown again by this checkout's planner (a
study, not the pipeline)

    .venv/bin/python experiments/studies/replan_study.py docs/table2_runs/seed0/results.json \\
        experiment=table2 seed=0

Reads each D-ICRL / C-ICRL learner's learned game from ``results.json`` (as
``prune_study.py`` does), checks that its learned set is the row's, and flies the row's
planned evaluation again: the run's evaluation starts and planner seed, ``eval_episodes``
episodes in the true game. Prints one JSON line per row, the committed SR and CVR beside
the ones flown now. A changed planner is measured this way on committed runs without
training them again.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

EXPERIMENTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXPERIMENTS))  # the entry points' common.py (studies/__init__.py)
from common import drone_task  # noqa: E402

from dicrl_torch.metrics import learned_constraints  # noqa: E402
from studies.prune_study import learned_games  # noqa: E402

CONFIGS = EXPERIMENTS.parent / "configs"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_intermixed_args(argv)
    results = json.loads(args.results.read_text())
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="train",
                      overrides=[*args.overrides, "solver.eval_policy=plan"])
    task = drone_task(cfg)
    for method, i, eta, cw in learned_games(results):
        row = results["methods"][method]["learners"][i]
        mask = learned_constraints(cw, task.threshold)
        if int(mask.sum()) != row["n_learned"]:
            raise SystemExit(
                f"{method} {i + 1}: the last history entry's ω_c learns {int(mask.sum())} "
                f"features where the row learned {row['n_learned']}; this run's results.json "
                f"does not hold its final ω_c.")
        t0 = time.perf_counter()
        flown, _ = task.evaluate_planned(task.base, eta, cw, mask, task.planning_seed())
        print(json.dumps({
            "method": method, "learner": i + 1,
            "committed": {"SR": row["SR"], "CVR": row["CVR"]},
            "now": {"SR": flown["SR"], "CVR": flown["CVR"]},
            "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
