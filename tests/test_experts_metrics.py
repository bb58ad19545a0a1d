"""Experts, demonstrations, local estimates, metrics and the benchmark CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from dicrl_torch.demos import PAPER_SPLIT, partition_demonstrations
from dicrl_torch.demos.features import discounted_feature_sums, local_estimates
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.metrics import (
    false_negative_rate,
    false_positive_rate,
    learned_constraints,
    reward_function_distance,
    rollout_true_cmg,
    true_cmg_step,
)
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman


def true_violations(layout: GridLayout, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """[m] bool: the episode breaks a true constraint (checked from scratch)."""
    obstacle = layout.obstacle_mask()[states].any((1, 2))
    forbidden = layout.forbidden_action_mask()[actions].any((1, 2))
    collision = np.zeros(len(states), dtype=bool)
    N = states.shape[2]
    for i in range(N):
        for j in range(i + 1, N):
            collision |= (states[:, :, i] == states[:, :, j]).any(1)
    return obstacle | forbidden | collision


def experts(n: int, constrained: bool, horizon: int = 40):
    layout = GridLayout.scobee(n)
    model = TabularGridModel(layout=layout, horizon=horizon, gamma=0.99)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64 if n < 3 else torch.float32)
    rb = GoalClosenessRewardBasis(model)
    sol = expert_solution(solver=solver, reward_features=rb(), reward_weights=rb.true_weights(),
                          constrained=constrained)
    return layout, model, rb, sol


@pytest.mark.parametrize("n,horizon", [(1, 40), (2, 40), (2, 12),
                                       pytest.param(3, 40, marks=pytest.mark.slow)])
def test_experts_never_violate_nominal_experts_do(n, horizon):
    # horizon 12: experts are still on their way at the last step, where nothing is
    # scored but the terminal value, which must keep them out of forbidden states.
    layout, _, _, sol = experts(n, constrained=True, horizon=horizon)
    demos = sample_trajectories(sol, 200, np.random.default_rng(0))
    assert not true_violations(layout, demos.states, demos.actions).any()
    _, _, _, nominal = experts(n, constrained=False, horizon=horizon)
    demos_nom = sample_trajectories(nominal, 200, np.random.default_rng(0))
    assert true_violations(layout, demos_nom.states, demos_nom.actions).mean() > 0.95


def test_sampling_is_deterministic_per_seed():
    _, _, _, sol = experts(2, constrained=True, horizon=10)
    a = sample_trajectories(sol, 20, np.random.default_rng(5))
    b = sample_trajectories(sol, 20, np.random.default_rng(5))
    c = sample_trajectories(sol, 20, np.random.default_rng(6))
    assert a == b and a != c


def test_local_estimates_partition_and_match_the_model():
    _, model, rb, sol = experts(2, constrained=True, horizon=12)
    demos = sample_trajectories(sol, 100, np.random.default_rng(1))
    shards = partition_demonstrations(demos, PAPER_SPLIT)
    cb = SharedIndicatorCostBasis(model)
    sums = discounted_feature_sums(cb(), demos, model.gamma)
    # the 10/20/30/40 local means, weighted by shard size, give the global mean
    local = [local_estimates(cb(), s, model.gamma) for s in shards]
    glob = sum(len(s.states) * mu for s, mu in zip(shards, local, strict=True)) / 100
    assert torch.allclose(glob, sums.mean(0))
    # a hand-computed entry: discounted count of the start cell of expert 1
    start = model.start_state[0]
    hand = sum(model.gamma**t * ((demos.states[0, t] == start).sum())
               for t in range(model.horizon))
    assert sums[0, start].item() == pytest.approx(hand)
    # demonstrations accrue no true-constraint feature
    assert sums[:, cb.true_constraints()].abs().max() == 0
    # soft experts' model expectation close to the empirical mean of their samples
    soft = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        rb().weighted(rb.true_weights()))
    soft_demos = sample_trajectories(soft, 4000, np.random.default_rng(2))
    emp = local_estimates(rb(), soft_demos, model.gamma)
    assert torch.allclose(emp, soft.feature_expectation(rb()), atol=0.1)


def test_constraint_rates_and_rfd():
    true = np.array([1, 1, 0, 0, 1], dtype=bool)
    assert false_positive_rate(np.array([1, 0, 1, 0, 0], bool), true) == 0.5
    assert false_negative_rate(np.array([1, 0, 1, 0, 0], bool), true) == pytest.approx(2 / 3)
    assert false_positive_rate(np.zeros(5, bool), true) == 0.0
    assert false_negative_rate(true, true) == 0.0
    assert learned_constraints(np.array([0.2, 0.5, 0.9])).tolist() == [False, True, True]
    # a weight at the threshold up to float rounding (a consensus mix of 0.5 and 0.5)
    assert learned_constraints(np.array([0.4999999999999993, 0.4999, 0.5])).tolist() == [
        True, False, True]
    assert reward_function_distance([1.0, 2.0], [1.0, 1.0]) == pytest.approx(1 / np.sqrt(2))
    with pytest.raises(TypeError):
        false_positive_rate(np.ones(5), true)
    with pytest.raises(ValueError, match="shape"):
        false_negative_rate(np.ones(4, bool), true)
    with pytest.raises(ValueError, match="threshold"):
        learned_constraints([0.1], threshold=0.0)


def test_true_cmg_step_semantics():
    layout = GridLayout.scobee(2)
    nxt = torch.from_numpy(layout.next_cell_table())
    E, NE = 3, 5
    cells = torch.tensor([[layout.cell((3, 8)), layout.cell((0, 0))],
                          [layout.cell((1, 1)), layout.cell((3, 1))],
                          [layout.cell((0, 0)), layout.cell((2, 0))]])
    acts = torch.tensor([[E, 0], [NE, 0], [E, 4]])
    moved = torch.ones(3, 2, dtype=torch.bool)
    active = torch.ones(3, 2, dtype=torch.bool)
    new, viol = true_cmg_step(layout, cells, acts, moved, active, nxt)
    assert viol[0].tolist() == [True, False]  # walked into obstacle (4,8)
    assert viol[1].tolist() == [True, False] and new[1, 0] == cells[1, 0]  # NE: no move
    assert viol[2].tolist() == [True, True]  # both land on (1,0)
    frozen = torch.tensor([[True, True], [True, True], [True, False]])
    _, viol2 = true_cmg_step(layout, cells, acts, moved, frozen, nxt)
    assert viol2[2].tolist() == [False, False]  # a frozen expert neither moves nor collides


def test_rollouts_give_paper_like_expert_rows():
    layout, model, rb, sol = experts(2, constrained=True)
    _, _, _, nominal = experts(2, constrained=False)
    table = rb().weighted(rb.true_weights()).local[:, :, 0]  # [N, S1] state reward
    g = torch.Generator().manual_seed(0)
    ok = rollout_true_cmg(policy=sol.policy_at, model=model, layout=layout,
                          reward_table=table, n_episodes=200, rng=g)
    bad = rollout_true_cmg(policy=nominal.policy_at, model=model, layout=layout,
                           reward_table=table, n_episodes=200, rng=g)
    assert ok.cvr == 0.0 and bad.cvr >= 0.95
    assert ok.cr_mean > 3 * bad.cr_mean  # crashed nominal experts earn little


def test_bench_cli_prints_one_json_line():
    out = subprocess.run(
        [sys.executable, "-m", "dicrl_torch.bench", "solver", "--experts", "2", "--grid", "5",
         "--horizon", "3", "--repeat", "2"], capture_output=True, text=True, check=True)
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1
    rec = json.loads(lines[0])
    assert rec["pairs"] == 25**2 * 81
    for key in ("backward_sweep_s", "forward_sweep_s", "peak_rss_gb"):
        assert rec[key] > 0
    assert rec["device"] == "cpu" and rec["occupancy_mass_error"] < 1e-4
    bad = subprocess.run([sys.executable, "-m", "dicrl_torch.bench", "solver", "--experts", "4"],
                         capture_output=True, text=True)
    assert bad.returncode != 0 and "invalid choice" in bad.stderr


@pytest.mark.parametrize("constrained", [True, False])
@pytest.mark.parametrize("n", [2, 3])
def test_batched_step_agrees_with_the_pettingzoo_env(n, constrained):
    from dicrl_torch.envs.gridworld_env import GridWorldCMG

    layout = GridLayout.scobee(n)
    env = GridWorldCMG(layout=layout, horizon=30, p_success=1.0, constrained=constrained)
    rb = GoalClosenessRewardBasis(TabularGridModel(layout=layout, horizon=30))
    table = rb().weighted(rb.true_weights()).local[:, :, 0].numpy()
    nxt = torch.from_numpy(layout.next_cell_table())
    rng = np.random.default_rng(n)
    for episode in range(20):
        env.reset(seed=episode)
        cells = torch.tensor(layout.start_cells).unsqueeze(0)
        active = torch.ones(1, n, dtype=torch.bool)
        for _ in range(30):
            acts = rng.integers(0, 9, size=n)
            live = list(env.agents)
            _, rewards, _, _, infos = env.step({a: int(acts[env.possible_agents.index(a)])
                                               for a in live})
            for a in live:
                i = env.possible_agents.index(a)
                assert rewards[a] == pytest.approx(table[i, cells[0, i]])
            cells, viol = true_cmg_step(layout, cells, torch.from_numpy(acts).unsqueeze(0),
                                        torch.ones(1, n, dtype=torch.bool), active, nxt,
                                        constrained)
            for a in live:
                i = env.possible_agents.index(a)
                assert infos[a]["cell"] == int(cells[0, i])
                assert infos[a]["violation"] == bool(viol[0, i])
            if constrained:
                active &= ~viol
            if not env.agents:
                break
