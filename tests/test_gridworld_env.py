"""Tests of the PettingZoo grid-world CMG (docs/design.md §3)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from dicrl_torch.envs.grid import (
    ACTION_NAMES,
    SCOBEE_FORBIDDEN_ACTIONS,
    SCOBEE_OBSTACLES,
    GridLayout,
)
from dicrl_torch.envs.gridworld_env import GridWorldCMG, render_grid

A = {name: i for i, name in enumerate(ACTION_NAMES)}


def scobee_like(starts, goals, **kw) -> GridLayout:
    """The Scobee 9x9 obstacles and forbidden actions with custom starts and goals."""
    return GridLayout(size=9, starts=tuple(starts), goals=tuple(goals),
                      obstacles=SCOBEE_OBSTACLES, forbidden_actions=SCOBEE_FORBIDDEN_ACTIONS,
                      **kw)


def det_env(layout: GridLayout, **kw) -> GridWorldCMG:
    """A deterministic env (p_success = 1), reset with a fixed seed."""
    env = GridWorldCMG(layout=layout, p_success=1.0, **kw)
    env.reset(seed=0)
    return env


# ---- PettingZoo API -----------------------------------------------------------------
@pytest.mark.parametrize("constrained", [True, False])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_parallel_api(n, constrained):
    env = GridWorldCMG(layout=GridLayout.scobee(n), constrained=constrained, horizon=40)
    # The API test only warns on wrong dict keys; make that a failure.
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        parallel_api_test(env, num_cycles=60)


@pytest.mark.parametrize("constrained", [True, False])
def test_parallel_seed(constrained):
    parallel_seed_test(lambda: GridWorldCMG(layout=GridLayout.scobee(3), constrained=constrained))


def test_same_seed_same_actions_same_trajectory():
    def rollout(seed):
        env = GridWorldCMG(layout=GridLayout.scobee(3), p_success=0.5, constrained=False)
        env.reset(seed=seed)
        cells = []
        for t in range(20):
            _, _, _, _, infos = env.step({a: A["SE"] if t % 2 else A["E"] for a in env.agents})
            cells.append([infos[a]["cell"] for a in env.possible_agents])
        return cells

    assert rollout(3) == rollout(3)
    assert rollout(3) != rollout(4)


def test_success_rate_matches_p_success():
    env = GridWorldCMG(layout=GridLayout.open_grid(9, 1), p_success=0.8, horizon=10_000,
                       constrained=False)
    env.reset(seed=1)
    moves = 0
    n = 2000
    for _ in range(n):
        # Alternate E/W in the middle of the grid so every success shows as a move.
        before = env.state()[0]
        env.step({"expert_0": A["E"] if before % 9 <= 4 else A["W"]})
        moves += int(env.state()[0] != before)
    assert abs(moves / n - 0.8) < 0.04


def test_reset_obs_spaces_and_state():
    layout = GridLayout.scobee(3)
    env = GridWorldCMG(layout=layout)
    obs, infos = env.reset(seed=0)
    assert env.agents == ["expert_0", "expert_1", "expert_2"]
    np.testing.assert_array_equal(env.state(), layout.start_cells)
    for a in env.agents:
        assert env.observation_space(a).contains(obs[a])
        assert obs[a].dtype == np.int64
        assert env.action_space(a).n == 9
        assert infos[a] == {"violation": False, "cell": layout.start_cells[int(a[-1])]}
    assert env.violated == dict.fromkeys(env.possible_agents, False)


# ---- hand-checked dynamics ----------------------------------------------------------
def test_move_east_and_off_grid():
    layout = GridLayout.scobee(1)
    env = det_env(layout)
    obs, _, term, trunc, infos = env.step({"expert_0": A["E"]})
    assert infos["expert_0"] == {"violation": False, "cell": layout.cell((1, 8))}
    np.testing.assert_array_equal(obs["expert_0"], [layout.cell((1, 8))])
    assert not term["expert_0"] and not trunc["expert_0"]

    env = det_env(layout)
    for action in ("W", "S", "SW"):  # off the grid from (0, 8): stay
        _, _, term, _, infos = env.step({"expert_0": A[action]})
        assert infos["expert_0"] == {"violation": False, "cell": layout.cell((0, 8))}
        assert not term["expert_0"]


def test_forbidden_action_true_vs_nominal_game():
    layout = GridLayout.scobee(1)
    env = det_env(layout, constrained=True)
    _, _, term, _, infos = env.step({"expert_0": A["NE"]})
    assert term["expert_0"] and infos["expert_0"]["violation"]
    assert infos["expert_0"]["cell"] == layout.cell((0, 8))  # a refused action: no move
    assert env.agents == [] and env.violated["expert_0"]

    env = det_env(layout, constrained=False)
    _, _, term, _, infos = env.step({"expert_0": A["NE"]})
    assert not term["expert_0"] and infos["expert_0"]["violation"]
    assert infos["expert_0"]["cell"] == layout.cell((1, 7))
    assert env.agents == ["expert_0"] and env.violated["expert_0"]


@pytest.mark.parametrize("constrained", [True, False])
def test_obstacle(constrained):
    layout = scobee_like([(3, 8)], [(8, 8)])
    env = det_env(layout, constrained=constrained)
    _, _, term, _, infos = env.step({"expert_0": A["E"]})
    assert infos["expert_0"] == {"violation": True, "cell": layout.cell((4, 8))}
    assert term["expert_0"] is constrained
    assert env.agents == ([] if constrained else ["expert_0"])


@pytest.mark.parametrize("constrained", [True, False])
def test_collision_both_violate(constrained):
    layout = scobee_like([(0, 0), (2, 0)], [(8, 8), (0, 8)])
    env = det_env(layout, constrained=constrained)
    _, _, term, _, infos = env.step({"expert_0": A["E"], "expert_1": A["W"]})
    for a in ("expert_0", "expert_1"):
        assert infos[a] == {"violation": True, "cell": layout.cell((1, 0))}
        assert term[a] is constrained


def test_no_collision_constraint_when_disabled():
    layout = scobee_like([(0, 0), (2, 0)], [(8, 8), (0, 8)], collision_constraint=False)
    env = det_env(layout)
    _, _, term, _, infos = env.step({"expert_0": A["E"], "expert_1": A["W"]})
    assert not any(term.values()) and not any(i["violation"] for i in infos.values())


def test_frozen_body_is_removed_from_board():
    layout = scobee_like([(0, 1), (1, 1)], [(8, 8), (0, 8)])
    env = det_env(layout)
    # expert_0 takes a forbidden action: it stays at (0, 1) and is frozen.
    _, _, term, _, _ = env.step({"expert_0": A["NW"], "expert_1": A["stay"]})
    assert term == {"expert_0": True, "expert_1": False}
    # expert_1 walks onto the frozen expert's cell: no collision any more.
    _, rew, term, _, infos = env.step({"expert_1": A["W"]})
    assert set(rew) == {"expert_1"}
    assert infos["expert_1"] == {"violation": False, "cell": layout.cell((0, 1))}
    np.testing.assert_array_equal(env.state(), [layout.cell((0, 1))] * 2)


def test_reward_formula_at_pre_step_cell():
    # expert_0 one cell W of its goal, expert_1 on its goal.
    layout = scobee_like([(7, 8), (0, 0)], [(8, 8), (0, 0)])
    w = np.array([[1.5, 2.0], [0.5, 3.0]])
    env = det_env(layout, reward_weights=w)
    _, rew, _, _, infos = env.step({"expert_0": A["E"], "expert_1": A["stay"]})
    assert rew["expert_0"] == pytest.approx(1.5 * (1 - 1 / 8))  # paid at (7, 8), not the goal
    assert rew["expert_1"] == pytest.approx(0.5 + 3.0)
    assert infos["expert_0"]["cell"] == layout.cell((8, 8))
    _, rew, _, _, _ = env.step({"expert_0": A["stay"], "expert_1": A["S"]})
    assert rew["expert_0"] == pytest.approx(1.5 + 2.0)
    assert rew["expert_1"] == pytest.approx(0.5 + 3.0)
    # expert_1 is now at (0, 1): cheb 1 to its goal.
    _, rew, _, _, _ = env.step({"expert_0": A["stay"], "expert_1": A["stay"]})
    assert rew["expert_1"] == pytest.approx(0.5 * (1 - 1 / 8))

    # Shared [2] weights and the default (1, 2) broadcast to every expert.
    for weights, expect in (((1.0, 2.0), [[1.0, 2.0]] * 2), (None, [[1.0, 2.0]] * 2),
                            ([0.3, 0.7], [[0.3, 0.7]] * 2)):
        np.testing.assert_allclose(
            GridWorldCMG(layout=layout, reward_weights=weights).reward_weights, expect)
    env = GridWorldCMG(layout=layout)
    assert env.reward_table.shape == (2, 81)
    assert env.reward_table[0, layout.cell((0, 8))] == 0.0  # 8 cells away: closeness 0
    assert env.reward_table[0].argmax() == layout.cell((8, 8))


def test_violator_paid_then_no_reward():
    layout = scobee_like([(7, 8), (0, 0)], [(8, 8), (8, 0)])
    env = det_env(layout)
    _, rew, term, _, _ = env.step({"expert_0": A["NE"], "expert_1": A["E"]})
    assert term["expert_0"] and rew["expert_0"] == pytest.approx(1 - 1 / 8)
    for _ in range(3):
        obs, rew, term, trunc, infos = env.step({"expert_1": A["S"]})
        for d in (obs, rew, term, trunc, infos):
            assert set(d) == {"expert_1"}
    assert env.agents == ["expert_1"]
    assert env.violated == {"expert_0": True, "expert_1": False}
    env.reset()
    assert env.violated == {"expert_0": False, "expert_1": False}


def test_truncation_after_horizon():
    env = det_env(GridLayout.scobee(2), horizon=5)
    for t in range(1, 6):
        _, _, term, trunc, _ = env.step(dict.fromkeys(env.agents, A["stay"]))
        assert not any(term.values())
        assert all(trunc.values()) is (t == 5)
    assert env.agents == [] and env.timestep == 5
    assert env.step({}) == ({}, {}, {}, {}, {})


def test_invalid_actions_and_calls():
    env = GridWorldCMG(layout=GridLayout.scobee(2))
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"expert_0": 0, "expert_1": 0})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="expert_1"):
        env.step({"expert_0": 0})
    with pytest.raises(ValueError, match="out of range"):
        env.step({"expert_0": 9, "expert_1": 0})
    with pytest.raises(ValueError, match="int"):
        env.step({"expert_0": 1.5, "expert_1": 0})
    with pytest.raises(ValueError, match="Unknown agent"):
        env.step({"expert_0": 0, "expert_1": 0, "expert_7": 0})
    env.step({"expert_0": np.int64(3), "expert_1": 0})  # numpy ints are fine


# ---- rendering ----------------------------------------------------------------------
def test_render_rgb_array():
    env = GridWorldCMG(layout=GridLayout.scobee(3), render_mode="rgb_array")
    env.reset(seed=0)
    env.step(dict.fromkeys(env.agents, A["NE"]))  # every expert violates and freezes
    img = env.render()
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8
    assert img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) > 100
    with pytest.warns(UserWarning, match="render_mode"):
        assert GridWorldCMG(layout=GridLayout.scobee(1)).render() is None


def test_render_grid_heat_and_constraints():
    layout = GridLayout.scobee(2)
    plain = render_grid(layout)
    heat = render_grid(layout, heat=np.linspace(0, 1, 81), constraint_cells=[40, 31],
                       cells=[72, None], title="visitation")
    assert heat.dtype == np.uint8 and heat.ndim == 3 and heat.shape[2] == 3
    assert heat.shape != plain.shape or not np.array_equal(heat, plain)
    with pytest.raises(ValueError, match="heat"):
        render_grid(layout, heat=np.zeros(80))
    with pytest.raises(ValueError, match="constraint_cells"):
        render_grid(layout, constraint_cells=[81])


def test_render_grid_fills_cell_colours():
    layout = GridLayout.open_grid(5, 1)  # no obstacles; start (0, 4), goal (4, 4)
    cell, free = layout.cell((2, 2)), layout.cell((3, 2))

    def centre(c: int) -> tuple[int, int]:  # pixel of c's centre: that of its red cross
        img = render_grid(layout, constraint_cells=[c]).astype(int)
        ys, xs = np.nonzero((img[..., 0] > 200) & (img[..., 1] < 80) & (img[..., 2] < 80))
        return round(ys.mean()), round(xs.mean())

    img = render_grid(layout, cell_colours={cell: "#ff0000"})
    assert img.shape == render_grid(layout).shape
    assert (img[centre(cell)] == [255, 0, 0]).all()
    assert (img[centre(free)] == 255).all()  # its neighbour stays white
    assert np.array_equal(render_grid(layout, cell_colours={}), render_grid(layout))
    with pytest.raises(ValueError, match="cell_colours"):
        render_grid(layout, cell_colours={25: "red"})


# ---- constructor validation ---------------------------------------------------------
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"layout": "scobee"}, "layout"),
        ({"horizon": 0}, "horizon"),
        ({"horizon": 2.5}, "horizon"),
        ({"horizon": True}, "horizon"),
        ({"p_success": 0.0}, "p_success"),
        ({"p_success": 1.5}, "p_success"),
        ({"constrained": "yes"}, "constrained"),
        ({"reward_weights": [1.0, 2.0, 3.0]}, "reward_weights"),
        ({"reward_weights": [[1.0, 2.0]] * 3}, "reward_weights"),
        ({"reward_weights": [np.nan, 1.0]}, "finite"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_invalid_constructor_args(kwargs, match):
    kw = {"layout": GridLayout.scobee(2)} | kwargs
    with pytest.raises(ValueError, match=match):
        GridWorldCMG(**kw)
