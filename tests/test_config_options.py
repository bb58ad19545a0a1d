"""Every option of every config group runs end to end through ``experiments/train.py``.

A handful of tiny runs (one outer iteration; one expert, 2 learners, T = 8 on the grid;
a few SAC steps in the arena) together use every YAML file under ``configs/<group>/``;
:func:`test_the_runs_cover_every_option_on_disk` fails when an option is added without a
run that uses it. Each run names every group's option on its command line, so what it
covers is exactly what it composes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import tiny_train
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
GROUPS = ("env", "features/cost", "features/reward", "solver", "algo", "graph", "comm",
          "comm/compression", "logger", "baselines", "experiment")

# tests/tiny_train.py's grid job, one outer iteration; each run names its logger.
GRID_TINY = [o for o in tiny_train.TINY if not o.startswith(("algo.outer_iterations=",
                                                              "logger="))]
GRID_TINY += ["algo.outer_iterations=1"]
# The arena at SAC toy scale (as tests/test_drone_dicrl.py): 20-step episodes, tens of
# SAC steps per solve, one outer iteration of 2 inner steps.
DRONE_TINY = ["env.arena.max_steps=20", "eval_episodes=2", "solver.warmup_timesteps=60",
              "solver.timesteps=20", "solver.final_timesteps=20", "solver.n_eval_episodes=1",
              "solver.final_checks=2", "solver.final_restarts=2",
              "solver.solver.learning_starts=30", "solver.solver.batch_size=16",
              "solver.solver.net_arch=[16,16]", "algo.outer_iterations=1",
              "algo.inner_steps=2", "baselines.timesteps=20", "baselines.max_constraints=1"]

GRID_EXPERTS = ["Experts (ground truth)", "Experts (nominal)"]
DRONE_EXPERTS = ["Experts (ground truth)"]
BILEVEL = ["D-ICRL", "C-ICRL"]
# Every table row has these (None where a metric does not apply).
ROW_METRICS = ("CR_mean", "FPR", "FNR", "CVR", "RFD", "SR")


@dataclass(frozen=True)
class Run:
    """One end-to-end run: an option of every group, the tiny overrides, the table rows."""

    name: str
    options: dict[str, str]
    tiny: list[str]
    methods: list[str]
    # False: the cost basis has no ground-truth constraint set, so FPR and FNR are null.
    truth: bool = True
    extra: list[str] = field(default_factory=list)

    @property
    def drones(self) -> bool:
        return self.options["env"] == "drones"


RUNS = [
    Run("grid-quick-per_expert-ring",
        {"experiment": "quick", "env": "gridworld", "features/reward": "goal_closeness",
         "features/cost": "per_expert", "solver": "factored", "algo": "dicrl",
         "graph": "ring", "comm": "simulated",
         "comm/compression": "lossless", "logger": "none", "baselines": "none"},
        GRID_TINY, [*BILEVEL, *GRID_EXPERTS]),
    Run("grid-quick_soft-shared-ring",
        {"experiment": "quick_soft", "env": "gridworld", "features/reward": "goal_closeness",
         "features/cost": "shared", "solver": "factored", "algo": "dicrl",
         "graph": "ring", "comm": "simulated",
         "comm/compression": "int8", "logger": "none", "baselines": "none"},
        GRID_TINY, [*BILEVEL, *GRID_EXPERTS]),
    Run("grid-table1-open-regions-greedy",
        {"experiment": "table1", "env": "gridworld_open", "features/reward": "goal_closeness",
         "features/cost": "regions", "solver": "factored", "algo": "dicrl",
         "graph": "directed_cycle", "comm": "simulated",
         "comm/compression": "lossless", "logger": "tensorboard",
         "baselines": "greedy"},
        GRID_TINY, [*BILEVEL, "ME-greedy", "MCE-greedy", *GRID_EXPERTS]),
    Run("grid-table1_small-local_relu_grid-complete",
        {"experiment": "table1_small", "env": "gridworld", "features/reward": "goal_closeness",
         "features/cost": "local_relu_grid", "solver": "factored", "algo": "dicrl",
         "graph": "complete", "comm": "simulated",
         "comm/compression": "lossless", "logger": "tensorboard",
         "baselines": "greedy"},
        GRID_TINY, [*BILEVEL, "ME-greedy", "MCE-greedy", *GRID_EXPERTS], truth=False,
        # a basis without per-feature truth, under the paper's rule
        extra=["algo.constraint_rule=threshold"]),
    Run("grid-quick_varied-shared-time_varying",
        {"experiment": "quick_varied", "env": "gridworld_varied",
         "features/reward": "goal_closeness", "features/cost": "shared", "solver": "factored",
         "algo": "dicrl", "graph": "time_varying", "comm": "simulated",
         "comm/compression": "lossless", "logger": "none",
         "baselines": "none"},
        GRID_TINY, [*BILEVEL, *GRID_EXPERTS]),
    Run("drones-table2_quick-fourier-local_relu_drones-greedy",
        {"experiment": "table2_quick", "env": "drones", "features/reward": "fourier",
         "features/cost": "local_relu_drones", "solver": "sac", "algo": "dicrl",
         "graph": "time_varying", "comm": "simulated",
         "comm/compression": "lossless", "logger": "none",
         "baselines": "greedy_drones"},
        # no per-feature truth: FPR and FNR null, the region scores instead; the learners
        # plan, growing the local units by the planner's margin
        DRONE_TINY, [*BILEVEL, "M(C)E-greedy", *DRONE_EXPERTS], truth=False),
    Run("drones-table2-door_location-cells",
        {"experiment": "table2", "env": "drones", "features/reward": "door_location",
         "features/cost": "cells", "solver": "sac", "algo": "dicrl", "graph": "ring",
         "comm": "simulated",
         "comm/compression": "int8", "logger": "tensorboard", "baselines": "none"},
        DRONE_TINY, [*BILEVEL, *DRONE_EXPERTS]),
]

# Options whose end-to-end run is another test's (group, option) -> that test. The
# spawned learner processes (one per learner) of comm=distributed: the `spawned` fixture
# there runs this file's grid job with comm=distributed and compares it with comm=simulated.
COVERED_ELSEWHERE = {
    ("comm", "distributed"):
        "tests/test_train_distributed.py::test_spawned_learners_reproduce_the_simulated_run",
    # its tiny run (the first 2 of its 3 experts, T = 8) is in the varied-start tests
    ("experiment", "table1_varied"):
        "tests/test_varied_start.py::test_table1_varied_runs_one_outer_iteration_at_reduced_scale",
    # the constrained MPE spread, through the runner at tiny scale with both cost bases
    **{option: "tests/test_mpe_task.py::test_the_mpe_quick_config_runs_end_to_end"
       for option in [("env", "mpe_spread"), ("experiment", "mpe_quick"),
                      ("features/reward", "landmark_coverage"),
                      ("features/cost", "position_cells"), ("features/cost", "local_relu")]},
}


def options_on_disk() -> set[tuple[str, str]]:
    return {(g, p.stem) for g in GROUPS for p in (CONFIGS / g).glob("*.yaml")}


def test_the_runs_cover_every_option_on_disk():
    groups = {str(p.parent.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml")
              if p.parent != CONFIGS}
    assert groups == set(GROUPS), "a config group was added or removed: update GROUPS"
    for run in RUNS:
        assert set(run.options) == set(GROUPS), f"{run.name} must name every group's option"
    used = {(g, o) for run in RUNS for g, o in run.options.items()} | set(COVERED_ELSEWHERE)
    on_disk = options_on_disk()
    missing = sorted(on_disk - used)
    assert not missing, (f"config options without an end-to-end run: "
                         f"{[f'{g}={o}' for g, o in missing]}; add each to a run of RUNS "
                         f"(tests/test_config_options.py) with an experiment it fits")
    assert not used - on_disk, f"RUNS name options that do not exist: {sorted(used - on_disk)}"
    for (group, option), test in COVERED_ELSEWHERE.items():
        path, name = test.split("::")
        text = (ROOT / path).read_text()
        assert f"def {name}(" in text and f'"{group}={option}"' in text, test


def _targets(node, path: str = "") -> dict[str, str]:
    """Every ``_target_`` below ``node``, by its path."""
    if not isinstance(node, dict):
        return {}
    found = {path: node["_target_"]} if "_target_" in node else {}
    for key, value in node.items():
        if key != "_target_":
            found.update(_targets(value, f"{path}.{key}"))
    return found


def _check_value(where: str, value) -> None:
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, int | float):
        assert math.isfinite(value), f"{where}={value}"
    elif isinstance(value, list):
        for i, x in enumerate(value):
            _check_value(f"{where}[{i}]", x)
    elif isinstance(value, dict):
        for k, x in value.items():
            _check_value(f"{where}.{k}", x)


@pytest.mark.parametrize("run", RUNS, ids=[r.name for r in RUNS])
def test_every_option_runs_end_to_end(run: Run, tmp_path):
    overrides = [f"{g}={o}" for g, o in run.options.items()]
    out = tiny_train.train_cli(tmp_path, *overrides, *run.tiny, *run.extra)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    methods = res["methods"]
    assert list(methods) == run.methods

    # the options composed are the ones named: their classes and the experiment's name
    for group, option in run.options.items():
        yaml = OmegaConf.to_container(OmegaConf.load(CONFIGS / group / f"{option}.yaml"))
        if group == "experiment":
            assert res["experiment"] == yaml["name"]
            continue
        node = res["config"]
        for part in group.split("/"):
            node = node[part]
        assert set(yaml) - {"defaults"} <= set(node), (group, option)  # composed away
        for path, target in _targets(yaml).items():
            assert _targets(node).get(path) == target, (group, option, path)

    learned = [m for m in run.methods if m not in (GRID_EXPERTS + DRONE_EXPERTS)]
    applies = {"CVR", "SR" if run.drones else "CR_mean"}
    rates = ("FPR", "FNR", "FPR_before_pruning", "FNR_before_pruning")
    for name, method in methods.items():
        assert method["learners"], name
        for v, row in enumerate(method["learners"]):
            where = f"{name} learner {v + 1}"
            _check_value(where, row)  # finite or null
            assert set(ROW_METRICS) <= set(row), (where, sorted(row))
            if name not in learned:
                continue
            for key in applies | ({"FPR", "FNR"} if run.truth else set()):
                assert row[key] is not None, (where, key)
            if not run.truth:  # no ground-truth constraint set: the rates do not apply
                assert all(row.get(k) is None for k in rates), (where, row)
            if run.drones:  # the game's truth scores any basis's learned set as a region
                assert 0 <= row["region_recall"] <= 1, (where, row)
                assert 0 <= row["region_precision"] <= 1, (where, row)
    assert len(methods["D-ICRL"]["learners"]) == 2
    for name, history in res["history"].items():
        assert history, name
        _check_value(f"history {name}", history)
        for entry in history:
            for key in ("FPR", "FNR"):
                values = entry[key] if isinstance(entry[key], list) else [entry[key]]
                assert all((x is None) != run.truth for x in values), (name, entry)
    if not run.truth:
        assert "N/A" in out.stdout.split("D-ICRL 1", 1)[1].splitlines()[0]
