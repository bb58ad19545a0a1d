"""Study: which learned drone constraints does planning need? (a study, not the pipeline)

    .venv/bin/python experiments/studies/prune_study.py docs/table2_runs/seed0/results.json \\
        --episodes 10 experiment=table2 seed=0

Reads each D-ICRL / C-ICRL learner's learned game (η̄ = reward_weights + multiplier, ω_c =
the last history entry) from a finished run's ``results.json`` and, for every feature of
its learned set (ω_c >= 0.5), plans in the nominal arena on the learned game with that one
feature removed (ω_c,j = 0, not forbidden), and counts the episodes whose paths enter it. A
feature no plan enters even when it is allowed is one the learned game does not need.
Prints one JSON line per feature.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

EXPERIMENTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXPERIMENTS))  # the entry points' common.py (studies/__init__.py)
from common import drone_task  # noqa: E402

CONFIGS = EXPERIMENTS.parent / "configs"


def learned_games(results: dict):
    """Yield (method, learner index, η [l_r + 1], ω_c [l_c]) of the planning rows."""
    for method in ("D-ICRL", "C-ICRL"):
        rows = results["methods"][method]["learners"]
        last = results["history"][method][-1]["cost_weights"]  # [learners][l_c]
        for i, row in enumerate(rows):
            eta = np.array([*row["reward_weights"], row["multiplier"]], dtype=np.float64)
            yield method, i, eta, np.asarray(last[i], dtype=np.float64)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--only", nargs="*", default=None,
                        help="METHOD:LEARNER:FEATURE entries to test (default: all)")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_intermixed_args(argv)
    results = json.loads(args.results.read_text())
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="train", overrides=[
            *args.overrides, f"eval_episodes={args.episodes}", "solver.eval_policy=plan"])
    task = drone_task(cfg)
    names = list(task.cost_basis.names)
    truth = task.cost_basis.true_constraints().numpy()
    for method, i, eta, cw in learned_games(results):
        learned = cw >= 0.5
        for j in np.flatnonzero(learned):
            if args.only is not None and f"{method}:{i}:{names[j]}" not in args.only:
                continue
            t0 = time.perf_counter()
            allowed = learned.copy()
            allowed[j] = False
            without = cw.copy()
            without[j] = 0.0  # neither forbidden nor penalised
            # The evaluation's common starts and planner streams, the same for every
            # feature; flown in the nominal arena (the learned game's own world).
            ev = task.base.evaluate(task.eval_episodes, true_game=False, trajectories=True,
                                    rng=task.evaluation_rng(),
                                    actor=task.planning_actor(eta, without, allowed, seed=0))
            entered = 0
            for path in ev.paths:
                phi = task.cost_basis.compute(torch.as_tensor(np.asarray(path))).numpy()
                entered += bool((phi[:, j] > 0).any())
            print(json.dumps({"method": method, "learner": i, "feature": names[j],
                              "true": bool(truth[j]), "omega_c": round(float(cw[j]), 3),
                              "episodes_entering": entered, "episodes": args.episodes,
                              "SR_nominal": ev.success_rate,
                              "s": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
