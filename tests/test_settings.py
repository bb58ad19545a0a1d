"""The settings' rules from plain Python (no config): each library constructor refuses a
value out of range with :class:`~dicrl_torch.checks.InvalidSetting`, whose message names the
argument, the value, what it must be and an example; a config reports the same error under
its own key (tests/test_robustness.py, tests/test_drone_dicrl.py)."""

from __future__ import annotations

import pickle

import pytest

from dicrl_torch.algos.dicrl import StepSizes, check_trainer_options
from dicrl_torch.checks import InvalidSetting
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.metrics import check_threshold, learned_constraints
from dicrl_torch.runs.runner import RunSettings, TrainerSpec
from dicrl_torch.runs.settings import LastSolve, WarmUp, check_split
from dicrl_torch.solvers.drone_planning import DronePlannerSettings
from dicrl_torch.solvers.planning import check_plan_sizes

SIZES = dict(horizon=30, knot=5, replan=1, samples=256, iterations=4, elites=25)
LAYOUT = GridLayout.open_grid(3, 1)


def run_settings(**changes) -> RunSettings:
    return RunSettings(**{"experiment": "x", "config": {}, "training_config": {},
                          "outer_iterations": 2, **changes})


def grid_settings(**changes):
    from dicrl_torch.runs.grid import GridTask

    return GridTask.check_settings(**{"split": [2, 3], "seed": 0, "eval_episodes": 10,
                                      **changes})


def sac_settings(**changes):
    from dicrl_torch.runs.continuous import SACTask

    return SACTask.check_settings(**{"split": [2, 3], "seed": 0, "timesteps": 20, **changes})


@pytest.mark.parametrize("make,name,must", [
    (lambda: GridLayout.scobee(n_experts=4), "n_experts", "1, 2 or 3"),
    (lambda: GridLayout.open_grid(size=1, n_experts=1), "size", "int >= 2"),
    (lambda: TabularGridModel(layout=LAYOUT, horizon=2.5), "horizon", "int >= 1"),
    (lambda: TabularGridModel(layout=LAYOUT, gamma=0.0), "gamma", "(0, 1]"),
    (lambda: TabularGridModel(layout=LAYOUT, p_success=float("nan")), "p_success", "(0, 1]"),
    (lambda: StepSizes(beta_power=0.5), "beta_power", "Theorem 1"),
    (lambda: StepSizes(alpha_bar=float("inf")), "alpha_bar", "positive"),
    (lambda: check_trainer_options(inner_steps=1), "inner_steps", "int >= 2"),
    (lambda: check_trainer_options(inner_method="newton"), "inner_method",
     "one of 'paper', 'tracking', 'gradient_tracking'"),
    (lambda: check_trainer_options(init_cost_weights=1.5), "init_cost_weights", "[0, 1]"),
    (lambda: TrainerSpec(schedules=None, steps=StepSizes(), inner_step=-1.0, n_shards=2),
     "inner_step", "positive"),
    (lambda: run_settings(outer_iterations=0), "outer_iterations", "int >= 1"),
    (lambda: run_settings(resume="yes"), "resume", "true or false"),
    (lambda: check_threshold(0.0), "threshold", "(0, 1]"),
    (lambda: learned_constraints([0.1], threshold=1.5), "threshold", "(0, 1]"),
    (lambda: check_split([3, 0]), "split", "ints >= 1"),
    (lambda: grid_settings(expert_temperature=-1.0), "expert_temperature", ">= 0"),
    (lambda: grid_settings(prune_min_gain=-1.0), "prune_min_gain", "null"),
    (lambda: grid_settings(baselines=["M-greedy"]), "baselines", "ME-greedy"),
    (lambda: grid_settings(baseline_max_constraints=1.5), "baseline_max_constraints",
     "int >= 0"),
    (lambda: sac_settings(timesteps=0), "timesteps", "int >= 1"),
    (lambda: sac_settings(eval_action="greedy"), "eval_action", "'mean' or 'sampled'"),
    (lambda: sac_settings(final_score="best"), "final_score", "learned_success"),
    (lambda: sac_settings(baseline_penalty=0.0), "baseline_penalty", "positive"),
    (lambda: WarmUp(timesteps=10, restarts=1, checks=20), "warmup_checks",
     "[1, warmup_timesteps=10]"),
    (lambda: LastSolve(timesteps=10, checks=2, restarts=1, score="penalised_return",
                       margin=0.5), "final_margin", "[0, 0.5)"),
    (lambda: check_plan_sizes(**{**SIZES, "elites": 300}), "elites", "at most samples=256"),
    (lambda: DronePlannerSettings(margin=0.3, grid_step=0.5), "grid_step",
     "margin=0.3 + half of it below half a cell"),
])
def test_a_constructor_refuses_a_value_naming_the_argument_and_the_fix(make, name, must):
    with pytest.raises(InvalidSetting) as info:
        make()
    e = info.value
    assert e.name == name and str(e).startswith(f"{name}=") and must in str(e), str(e)
    assert f"set e.g. {name}=" in str(e)


def test_distributed_settings_are_refused_before_any_process_group():
    from dicrl_torch.comm.distributed import DistributedCommunicator

    with pytest.raises(InvalidSetting, match="timeout_s=0 is invalid: it must be a positive"):
        DistributedCommunicator(timeout_s=0)
    with pytest.raises(InvalidSetting, match="backend='mpi' is invalid"):
        DistributedCommunicator.check_settings(backend="mpi")


def test_a_renamed_error_names_every_setting_by_its_key_and_pickles():
    with pytest.raises(InvalidSetting) as info:
        check_plan_sizes(**{**SIZES, "replan": 2})
    keys = {k: f"solver.planner.{k}" for k in SIZES}
    renamed = info.value.renamed(keys)
    assert str(renamed).startswith("solver.planner.replan=2 is invalid: it must be an int "
                                   ">= 1 dividing solver.planner.knot=5")
    assert str(renamed).endswith("set e.g. solver.planner.replan=5.")
    assert str(pickle.loads(pickle.dumps(renamed))) == str(renamed)


def test_the_threshold_may_be_the_weights_upper_bound():
    """ω_c lives in [0, 1]: threshold 1 marks the weights at the bound (one rule, the
    metrics', for the tasks and the config alike)."""
    assert learned_constraints([1.0, 0.99], threshold=1.0).tolist() == [True, False]
    assert grid_settings(threshold=1.0).threshold == 1.0


def test_the_tasks_settings_are_grouped_and_normalised():
    s = sac_settings(warmup_timesteps=60, warmup_restarts=3, warmup_checks=2,
                     baseline=True, baseline_epsilon=0, planner={"replan": 5})
    assert s.warmup == WarmUp(timesteps=60, restarts=3, checks=2)
    assert s.last_solve.timesteps == 20  # final_timesteps None: the inner solves'
    assert s.rollouts.planner == {"replan": 5} and s.split == (2, 3)
    assert s.baseline.run and s.baseline.epsilon == 0.0
    g = grid_settings(baselines=["MCE-greedy"])
    assert g.baselines == ("MCE-greedy",) and g.constraint_rule == "certificate"
