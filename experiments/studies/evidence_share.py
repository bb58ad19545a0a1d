"""Study: how much of a game's forbidden region a policy that ignores the constraints shows
to ICRL (a study, not the pipeline)

    .venv/bin/python experiments/studies/evidence_share.py experiment=mpe_quick \\
        features/cost=local_relu seed=0 --episodes 40
    .venv/bin/python experiments/studies/evidence_share.py experiment=table2_quick \\
        features/cost=local_relu_drones seed=0

With budget 0 a cost feature becomes a constraint only as far as some learner's policy
accrues it. Per learner, this prints the share of the forbidden test states lying in a
feature that the learner could learn (``constrainable``: its demonstrations and the start
states never make it positive) *and* that a constraint-ignoring flight accrues: the MPE's
nominal controller (straight to the landmarks) over ``--episodes`` fresh starts in the
nominal game, or straight flights from every start of the drones' start support to their
doors' centres. Beside it, the share any constrainable feature covers (the expressivity
bound the run prints). A learner's policies can show more than these flights (they wander),
so the share is no bound; it says how much of the region the shortest ways in cross.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

EXPERIMENTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXPERIMENTS))  # the entry points' common.py (studies/__init__.py)
from common import build_task  # noqa: E402

from dicrl_torch.envs.drones.geometry import DOORS, ROOM_SIZE, start_support  # noqa: E402
from dicrl_torch.region import feature_support  # noqa: E402
from dicrl_torch.runs.drones import DroneTask  # noqa: E402
from dicrl_torch.runs.mpe import MPETask, NominalController  # noqa: E402

CONFIGS = EXPERIMENTS.parent / "configs"


def straight_flights(points: int = 200) -> np.ndarray:
    """``[F, points, 2, 4]`` one drone flying straight at rest from each start of its start
    support to its door's centre, the other far outside the room (where no feature of
    its fires)."""
    starts = start_support()[:, :, :2]
    flights = []
    for d, (lo, hi) in enumerate(DOORS):
        door = np.array([(lo + hi) / 2, ROOM_SIZE])
        for start in np.unique(starts[:, d], axis=0):
            t = np.linspace(0.0, 1.0, points)[:, None]
            states = np.zeros((points, len(DOORS), 4))
            states[:, :, :2] = -10.0 * ROOM_SIZE
            states[:, d, :2] = start + t * (door - start)
            flights.append(states)
    return np.stack(flights)


def accrued(task, episodes: int, seed: int) -> np.ndarray:
    """``[l_c]`` bool: the cost features a constraint-ignoring flight makes positive."""
    if isinstance(task, DroneTask):
        states = straight_flights().reshape(-1, len(DOORS), 4)
    elif isinstance(task, MPETask):
        seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=episodes)
        flown = task._fly(NominalController, seeds.tolist(), constrained=False)
        states = np.concatenate([np.asarray(e.states[1:]) for e in flown])
    else:
        raise SystemExit(f"{type(task).__name__}: no constraint-ignoring flight is defined "
                         f"here (the drones and the MPE spread).")
    return feature_support(task.cost_basis, states).any(0)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=40,
                        help="the MPE nominal controller's episodes (fresh starts)")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_intermixed_args(argv)
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="train", overrides=args.overrides)
    task = build_task(cfg)
    test = task.region_test()
    if test is None:
        raise SystemExit("the game has no region truth (region_truth() is None).")
    shown = accrued(task, args.episodes, seed=1000 + int(cfg.seed))
    support = test["support"][test["forbidden"]]  # [M_forbidden, l_c]
    records = []
    for v, usable in enumerate(task.constrainable()):
        records.append({
            "learner": "C-ICRL" if v == len(task.shards) else v + 1,
            "expressible": float(support[:, usable].any(1).mean()),
            "shown_by_ignoring_flights": float(support[:, usable & shown].any(1).mean())})
        print(json.dumps(records[-1]), flush=True)
    return records


if __name__ == "__main__":
    main()
