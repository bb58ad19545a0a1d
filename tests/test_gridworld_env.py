"""The PettingZoo grid-world CMG: API checkers, hand-checked dynamics and rendering."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from dicrl_torch.envs.grid import ACTION_NAMES, GridLayout
from dicrl_torch.envs.gridworld_env import GridWorldCMG, render_grid

A = {name: i for i, name in enumerate(ACTION_NAMES)}


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("constrained", [True, False])
def test_parallel_api(n, constrained):
    env = GridWorldCMG(layout=GridLayout.scobee(n), horizon=30, constrained=constrained)
    parallel_api_test(env, num_cycles=200)


@pytest.mark.parametrize("n", [1, 3])
def test_parallel_seed(n):
    parallel_seed_test(lambda: GridWorldCMG(layout=GridLayout.scobee(n), horizon=20))


def step_all(env, **acts):
    return env.step({a: acts.get(a, A["stay"]) for a in env.agents})


def test_moves_off_grid_and_rewards():
    layout = GridLayout.scobee(1)
    env = GridWorldCMG(layout=layout, horizon=5, p_success=1.0)
    obs, _ = env.reset(seed=0)
    assert obs["expert_0"].tolist() == [layout.cell((0, 8))]
    _, rew, _, _, infos = step_all(env, expert_0=A["E"])
    assert infos["expert_0"]["cell"] == layout.cell((1, 8))
    assert rew["expert_0"] == pytest.approx(1.0 * (1 - 8 / 8))  # pre-step cell, 8 away
    _, rew, _, _, infos = step_all(env, expert_0=A["S"])  # off the grid: stays
    assert infos["expert_0"]["cell"] == layout.cell((1, 8))
    assert rew["expert_0"] == pytest.approx(1 - 7 / 8)


def test_goal_reward_and_truncation():
    layout = GridLayout(size=3, starts=((0, 0),), goals=((0, 0),))
    env = GridWorldCMG(layout=layout, horizon=3)
    env.reset(seed=0)
    for t in range(3):
        _, rew, term, trunc, _ = step_all(env)
        assert rew["expert_0"] == pytest.approx(1.0 + 2.0)  # closeness 1 + at goal
        assert trunc["expert_0"] == (t == 2) and not term["expert_0"]
    assert env.agents == []


def test_forbidden_action_stops_only_in_true_cmg():
    layout = GridLayout.scobee(1)
    for constrained in (True, False):
        env = GridWorldCMG(layout=layout, horizon=5, p_success=1.0, constrained=constrained)
        env.reset(seed=0)
        _, _, term, _, infos = step_all(env, expert_0=A["NE"])
        assert infos["expert_0"]["violation"]
        assert term["expert_0"] == constrained
        moved = infos["expert_0"]["cell"] != layout.cell((0, 8))
        assert moved == (not constrained)  # refused in the true CMG


def test_obstacle_and_collision_violations():
    layout = GridLayout(size=9, starts=((3, 8), (6, 0)), goals=((8, 8), (0, 0)),
                        obstacles=((4, 8),))
    env = GridWorldCMG(layout=layout, horizon=5, p_success=1.0)
    env.reset(seed=0)
    _, rew, term, _, infos = step_all(env, expert_0=A["E"])
    assert infos["expert_0"]["violation"] and term["expert_0"]
    assert "expert_0" not in env.agents and env.violated["expert_0"]
    assert "expert_0" in rew  # the violating step is still paid
    # the frozen expert earns nothing more
    _, rew, _, _, _ = step_all(env)
    assert set(rew) == {"expert_1"}

    layout2 = GridLayout(size=3, starts=((0, 0), (2, 0)), goals=((2, 2), (0, 2)))
    env2 = GridWorldCMG(layout=layout2, horizon=5, p_success=1.0)
    env2.reset(seed=0)
    _, _, term, _, _ = step_all(env2, expert_0=A["E"], expert_1=A["W"])  # both to (1,0)
    assert term == {"expert_0": True, "expert_1": True}


def test_render_and_render_grid():
    env = GridWorldCMG(layout=GridLayout.scobee(3), render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    heat = np.random.default_rng(0).random(81)
    img2 = render_grid(env.layout, heat=heat, constraint_cells=[40, 3], title="heat")
    assert img2.shape[2] == 3 and img2.std() > 0
    with pytest.raises(ValueError, match="heat"):
        render_grid(env.layout, heat=np.zeros(5))


@pytest.mark.parametrize("kwargs,match", [
    ({"horizon": 0}, "horizon"),
    ({"p_success": 1.5}, "p_success"),
    ({"render_mode": "human"}, "render_mode"),
    ({"reward_weights": [1.0, 2.0, 3.0]}, "reward_weights"),
    ({"constrained": "yes"}, "constrained"),
])
def test_invalid_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GridWorldCMG(layout=GridLayout.scobee(2), **kwargs)


def test_actions_are_validated():
    env = GridWorldCMG(layout=GridLayout.scobee(2))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="No action"):
        env.step({"expert_0": 0})
    with pytest.raises(ValueError, match="out of range"):
        env.step({"expert_0": 0, "expert_1": 9})
