"""The varied-start protocol (docs/design.md §3): P0 spreads each expert's start uniformly
over a set of free cells, independently per expert. Checked against independent truth:
brute-force products and feature minima, empirical start frequencies of the samplers and
the env, and a copy of the fixed-start rollout loop for bit-identity."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch
from tiny_train import TRAIN, compose_train, train_cli

from dicrl_torch.algos.models import TabularLearnerModel
from dicrl_torch.demos import save_demonstrations
from dicrl_torch.envs.grid import (
    SCOBEE_OBSTACLES,
    SCOBEE_START_REGIONS,
    GridLayout,
    TabularGridModel,
    decode_joint,
)
from dicrl_torch.envs.gridworld_env import GridWorldCMG, render_grid
from dicrl_torch.features.bases import (
    GoalClosenessRewardBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.metrics import rollout_true_cmg, true_cmg_step
from dicrl_torch.runs.grid import load_shard_files
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

ROOT = TRAIN.parents[1]
# A 4x4 open grid, expert 1 in the bottom-left 2x2 block, expert 2 in the top-right one.
OPEN_REGIONS = [[0, 2, 1, 3], [2, 0, 3, 1]]


def open_varied(horizon: int = 6) -> TabularGridModel:
    return TabularGridModel(layout=GridLayout.open_grid(4, 2, start_regions=OPEN_REGIONS),
                            horizon=horizon, gamma=0.95)


def chi_square(counts: np.ndarray, probs: np.ndarray) -> float:
    expected = counts.sum() * probs
    return float(((counts - expected) ** 2 / expected).sum())


def chi_square_bound(dof: int) -> float:
    """Far in the upper tail (mean + 6 standard deviations of a χ² with ``dof``): the
    draws are seeded, so this only has to reject a wrong distribution, never flake."""
    return dof + 6.0 * np.sqrt(2.0 * dof)


def joint_index(cells: np.ndarray, base: int) -> np.ndarray:
    flat = np.zeros(cells.shape[0], dtype=np.int64)
    for i in range(cells.shape[1]):
        flat = flat * base + cells[:, i]
    return flat


# ---------------------------------------------------------------- P0 and its support
def test_p0_is_the_brute_force_product_of_uniform_start_sets():
    model = open_varied()
    layout = model.layout
    sets = [{(0, 2), (1, 2), (0, 3), (1, 3)}, {(2, 0), (3, 0), (2, 1), (3, 1)}]
    assert [set(s) for s in layout.start_sets] == sets
    p0 = model.initial_distribution()
    assert p0.shape == (16, 16) and p0.dtype == torch.float64
    assert float(p0.sum()) == pytest.approx(1.0, abs=1e-15)
    for s1, s2 in itertools.product(range(16), repeat=2):
        want = ((layout.xy(s1) in sets[0]) / 4) * ((layout.xy(s2) in sets[1]) / 4)
        assert float(p0[s1, s2]) == want
    support = model.start_support()
    assert support.dtype == torch.int64 and support.shape == (16, 2)
    assert torch.equal(support, torch.nonzero(p0))  # ascending joint index, mass > 0 only


@pytest.mark.parametrize("n", [1, 2, 3])
def test_scobee_varied_p0_sums_to_one_on_free_disjoint_cells(n):
    model = TabularGridModel(layout=GridLayout.scobee_varied(n), horizon=3)
    p0 = model.initial_distribution()
    assert p0.shape == (81,) * n and float(p0.sum()) == pytest.approx(1.0, abs=1e-12)
    support = model.start_support()
    assert support.shape == (int((p0 > 0).sum()), n)
    assert torch.allclose(p0.reshape(-1)[joint_index(support.numpy(), 81)],
                          torch.tensor(1.0 / support.shape[0], dtype=torch.float64))
    sets = model.layout.start_cell_sets
    for i, (x0, y0, x1, y1) in enumerate(SCOBEE_START_REGIONS[n]):
        free = {y * 9 + x for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)
                if (x, y) not in SCOBEE_OBSTACLES}
        assert set(sets[i]) == free
        assert model.layout.start_cells[i] in sets[i]
    assert sum(len(s) for s in sets) == len(set().union(*sets))  # disjoint


def test_fixed_starts_keep_a_point_mass():
    model = TabularGridModel(layout=GridLayout.scobee(2), horizon=3)
    old = torch.zeros(81, 81, dtype=torch.float64)
    old[model.start_state] = 1.0  # what P0 was before start sets existed
    assert torch.equal(model.initial_distribution(), old)
    assert model.start_support().tolist() == [list(model.start_state)]
    assert not model.layout.varied_start
    # singleton start sets are the same P0
    singletons = GridLayout.scobee(2).with_start_regions([[0, 8, 0, 8], [8, 0, 8, 0]])
    assert singletons.start_sets == (((0, 8),), ((8, 0),))
    assert torch.equal(TabularGridModel(layout=singletons, horizon=3).initial_distribution(),
                       old)


# ---------------------------------------------------------------- refusals
@pytest.mark.parametrize("start_sets,match", [
    ((((0, 3), (1, 3)), ((3, 0), (9, 0))), r"expert 2's start set: cells \[\(9, 0\)\] lie "
                                           r"outside the 4x4 grid"),
    ((((0, 3), (1, 1)), ((3, 0),)), r"expert 1's start set: cells \[\(1, 1\)\] are "
                                    r"obstacles.*remove them"),
    ((((0, 3), (2, 2)), ((3, 0), (2, 2))), r"cell \(2, 2\) is in the start sets of experts 1 "
                                           r"and 2.*collision.*disjoint"),
    ((((0, 3),), ()), r"expert 2's start set is empty; give it at least its start \(3, 0\)"),
    ((((0, 2),), ((3, 0),)), r"expert 1's start \(0, 3\) is not in its start set "
                             r"\[\(0, 2\)\]; add it"),
    ((((0, 3),),), r"start_sets gives 1 start set\(s\) for 2 expert\(s\); give one per expert"),
    ((((0, 3, 1),), ((3, 0),)), r"start_sets must hold one list of \(x, y\) cells per expert"),
])
def test_bad_start_sets_are_refused(start_sets, match):
    with pytest.raises(ValueError, match=match):
        GridLayout(size=4, starts=((0, 3), (3, 0)), goals=((3, 3), (0, 0)),
                   obstacles=((1, 1),), start_sets=start_sets)


@pytest.mark.parametrize("regions,match", [
    ([[0, 5, 3, 8]], r"start_regions gives 1 rectangle\(s\) for 2 experts; add one"),
    ([[0, 5, 3, 9], [5, 0, 8, 8]], r"start region \[0, 5, 3, 9\] of expert 1 is not a "
                                   r"rectangle .* inside the 9x9 grid"),
    ([[3, 5, 0, 8], [5, 0, 8, 8]], r"start region \[3, 5, 0, 8\] of expert 1 is not a rectangle"),
    ([[0, 5, 3, 8], [4, 0, 4, 2]], r"start region \[4, 0, 4, 2\] of expert 2 holds only "
                                   r"obstacles"),
    ([[1, 5, 3, 8], [5, 0, 8, 8]], r"start region \[1, 5, 3, 8\] of expert 1 does not contain "
                                   r"its start \(0, 8\); widen it"),
    ([[0, 0, 8, 8], [5, 0, 8, 8]], r"cell \(5, 0\) is in the start sets of experts 1 and 2"),
    ([[0, 5, 3]], r"start_regions must be one rectangle \[x0, y0, x1, y1\] per expert"),
    ("left", r"start_regions must be one rectangle"),
])
def test_bad_start_regions_are_refused(regions, match):
    with pytest.raises(ValueError, match=match):
        GridLayout.scobee(2, start_regions=regions)


def test_regions_skip_obstacles_and_extra_regions_are_unused():
    layout = GridLayout.scobee_varied(3, start_regions=[[0, 5, 3, 8], [5, 0, 8, 8],
                                                        [0, 0, 3, 4], [0, 0, 0, 0]])
    # (2,3) and (3,4) are obstacles: expert 3 gets the block's other 18 cells
    block = {(x, y) for x in range(4) for y in range(5)}
    assert set(layout.start_sets[2]) == block - {(2, 3), (3, 4)}
    assert len(layout.start_sets) == 3 and layout.name == "scobee3_varied"


def test_a_doomed_start_state_is_refused_by_the_experts():
    # Every action but E is forbidden: from (0,1) E enters the obstacle (1,1) with
    # probability 0.8, so no policy is safe there; from (0,0) it is.
    every_but_east = ("stay", "N", "S", "W", "NE", "NW", "SE", "SW")
    kw = dict(size=3, starts=((0, 0),), goals=((2, 0),), obstacles=((1, 1),),
              forbidden_actions=every_but_east)
    def experts(sets):
        model = TabularGridModel(layout=GridLayout(**kw, start_sets=sets), horizon=4)
        rb = GoalClosenessRewardBasis(model)
        return expert_solution(solver=FactoredSoftBellman(model=model, dtype=torch.float64),
                               reward_features=rb(), reward_weights=rb.true_weights())

    experts((((0, 0),),))  # the nominal start alone is safe
    with pytest.raises(ValueError, match=r"1 of the 2 start states P0 gives mass to, "
                                         r"e\.g\. \[\(0, 1\)\].*start sets"):
        experts((((0, 0), (0, 1)),))


# ---------------------------------------------------------------- sampling from P0
def open_experts(model: TabularGridModel):
    rb = GoalClosenessRewardBasis(model)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    return expert_solution(solver=solver, reward_features=rb(), reward_weights=rb.true_weights())


def test_sampled_trajectories_start_as_p0_says():
    model = open_varied()
    demos = sample_trajectories(open_experts(model), 4000, np.random.default_rng(3))
    starts = demos.states[:, 0]  # [n, N]
    flat = joint_index(starts, model.n_cells)
    p0 = model.initial_distribution().reshape(-1).numpy()
    assert (p0[flat] > 0).all()
    support = joint_index(model.start_support().numpy(), model.n_cells)
    counts = np.array([(flat == s).sum() for s in support])
    assert chi_square(counts, p0[support]) < chi_square_bound(len(support) - 1)
    # a wrong P0 (all mass split over half the support) is rejected by the same test
    wrong = np.where(np.arange(len(support)) < 8, 1 / 8, 1e-9)
    assert chi_square(counts, wrong / wrong.sum()) > chi_square_bound(len(support) - 1)


def test_env_reset_draws_the_start_from_p0_with_its_seeded_stream():
    layout = GridLayout.open_grid(4, 2, start_regions=OPEN_REGIONS)
    env = GridWorldCMG(layout=layout, horizon=5)
    env.reset(seed=11)
    starts = np.array([env.reset()[0]["expert_0"] for _ in range(4000)])
    flat = joint_index(starts, 16)
    model = TabularGridModel(layout=layout, horizon=5)
    p0 = model.initial_distribution().reshape(-1).numpy()
    assert (p0[flat] > 0).all()
    support = joint_index(model.start_support().numpy(), 16)
    counts = np.array([(flat == s).sum() for s in support])
    assert chi_square(counts, p0[support]) < chi_square_bound(len(support) - 1)
    # seeded: the same seed, the same start; the info reports it
    first = [GridWorldCMG(layout=layout).reset(seed=5)[1] for _ in range(2)]
    assert first[0] == first[1]


def test_env_with_varied_starts_passes_the_pettingzoo_tests():
    from pettingzoo.test import parallel_api_test, parallel_seed_test

    layout = GridLayout.scobee_varied(3)
    parallel_api_test(GridWorldCMG(layout=layout, horizon=40), num_cycles=60)
    parallel_seed_test(lambda: GridWorldCMG(layout=layout))
    image = render_grid(layout)
    assert image.ndim == 3 and image.shape[2] == 3


def fixed_start_rollout(*, policy, model, layout, reward_table, n_episodes, rng):
    """``rollout_true_cmg`` as it was before P0 could be spread: every episode from the
    fixed start, no draw before the first step (the reference for bit-identity)."""
    N, A1, T, B = model.n_experts, model.n_actions, model.horizon, n_episodes
    cells = torch.tensor(model.start_state, dtype=torch.int64).expand(B, N).clone()
    active = torch.ones(B, N, dtype=torch.bool)
    returns = torch.zeros(B, dtype=torch.float64)
    all_cells = torch.empty(B, T + 1, N, dtype=torch.int64)
    all_cells[:, 0] = cells
    for t in range(T):
        returns += (reward_table[torch.arange(N), cells].double() * active).sum(1)
        joint = torch.multinomial(policy(t, cells).double().cpu(), 1, generator=rng).squeeze(1)
        actions = decode_joint(joint, A1, N)
        moved = torch.rand(B, N, generator=rng, dtype=torch.float64) < model.p_success
        cells, violation = true_cmg_step(layout, cells, actions, moved, active, model.next_cell)
        active &= ~violation
        all_cells[:, t + 1] = cells
    return returns.numpy(), all_cells.numpy()


@pytest.mark.parametrize("singletons", [False, True])
def test_rollouts_with_a_point_mass_p0_are_bit_identical_to_fixed_starts(singletons):
    layout = GridLayout.open_grid(4, 2)
    if singletons:  # start sets of one cell each: still a point mass
        layout = layout.with_start_regions([[0, 3, 0, 3], [3, 0, 3, 0]])
    model = TabularGridModel(layout=layout, horizon=6, gamma=0.95)
    sol = open_experts(model)
    table = GoalClosenessRewardBasis(model)().weighted(
        GoalClosenessRewardBasis(model).true_weights()).local[:, :, 0]
    kw = dict(policy=sol.policy_at, model=model, layout=layout, reward_table=table,
              n_episodes=300)
    g_new, g_old = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    new = rollout_true_cmg(**kw, rng=g_new)
    ref_returns, ref_cells = fixed_start_rollout(**kw, rng=g_old)
    assert np.array_equal(new.returns, ref_returns) and np.array_equal(new.cells, ref_cells)
    assert torch.equal(g_new.get_state(), g_old.get_state())  # nothing extra drawn
    # the experts' samples too: every trajectory from the fixed start
    demos = sample_trajectories(sol, 50, torch.Generator().manual_seed(1))
    assert (demos.states[:, 0] == np.array(model.start_state)).all()


def test_rollouts_with_varied_starts_start_from_p0():
    model = open_varied()
    sol = open_experts(model)
    rb = GoalClosenessRewardBasis(model)
    ev = rollout_true_cmg(policy=sol.policy_at, model=model, layout=model.layout,
                          reward_table=rb().weighted(rb.true_weights()).local[:, :, 0],
                          n_episodes=4000, rng=torch.Generator().manual_seed(2))
    flat = joint_index(ev.cells[:, 0], 16)
    p0 = model.initial_distribution().reshape(-1).numpy()
    support = joint_index(model.start_support().numpy(), 16)
    counts = np.array([(flat == s).sum() for s in support])
    assert counts.sum() == 4000
    assert chi_square(counts, p0[support]) < chi_square_bound(len(support) - 1)
    assert not ev.violated.any()  # the experts are safe from every start


# ---------------------------------------------------------------- learners and files
@pytest.mark.parametrize("basis", [SharedIndicatorCostBasis, RegionIndicatorCostBasis])
def test_start_features_match_brute_force_over_the_start_support(basis):
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2, start_regions=[[0, 1, 1, 2],
                                                                              [2, 0, 2, 1]]),
                             horizon=3, gamma=0.9)
    kw = {"regions": {"corner": [[0, 0]], "left": [[0, 1], [0, 2]]}} \
        if basis is RegionIndicatorCostBasis else {}
    cost = basis(model, **kw)
    learner = TabularLearnerModel(solver=FactoredSoftBellman(model=model, dtype=torch.float64),
                                  reward_basis=GoalClosenessRewardBasis(model), cost_basis=cost)
    dense = cost().dense()  # [S, A, l]
    p0 = model.initial_distribution().reshape(-1)
    # positive at some start state with mass, whatever the joint action
    want = ((dense > 0).all(1) & (p0 > 0).unsqueeze(1)).any(0)
    got = learner.start_features()
    assert torch.equal(got, want)
    names = {n for n, g in zip(cost.names, got.tolist(), strict=True) if g}
    # every start cell of both experts and the region holding some; no action (another
    # action is free) and no collision (the sets are disjoint)
    cells = {"cell({},{})".format(*model.layout.xy(c)) for s in model.layout.start_cell_sets
             for c in s}
    assert len(cells) == 6
    assert names == cells | ({"region left"} if basis is RegionIndicatorCostBasis else set())


def test_start_features_of_fixed_starts_are_the_old_ones():
    model = TabularGridModel(layout=GridLayout.scobee(2), horizon=3)
    cost = SharedIndicatorCostBasis(model)
    learner = TabularLearnerModel(solver=FactoredSoftBellman(model=model),
                                  reward_basis=GoalClosenessRewardBasis(model), cost_basis=cost)
    actions = decode_joint(torch.arange(81), 9, 2)  # every joint action
    cells = torch.tensor(model.start_state).expand_as(actions)
    old = (cost().at(cells, actions, 81) > 0).all(0)  # the fixed-start computation
    assert torch.equal(learner.start_features(), old)
    assert int(old.sum()) == 2


def test_shard_files_must_start_where_p0_has_mass(tmp_path):
    model = open_varied()
    demos = sample_trajectories(open_experts(model), 6, np.random.default_rng(0))
    assert len({tuple(s) for s in demos.states[:, 0]}) > 1  # spread starts
    path = save_demonstrations(tmp_path / "varied.npz", demos)
    (shard,) = load_shard_files([str(path)], [6], model)
    assert np.array_equal(shard.states, demos.states)
    fixed = TabularGridModel(layout=GridLayout.open_grid(4, 2), horizon=6, gamma=0.95)
    k = int(np.nonzero((demos.states[:, 0] != np.array(fixed.start_state)).any(1))[0][0])
    with pytest.raises(ValueError, match=rf"varied\.npz': trajectory {k} starts in cells .*"
                                         rf"where P0 has no mass: expert \d .*use "
                                         rf"demonstrations recorded on this layout"):
        load_shard_files([str(path)], [6], fixed)


# ---------------------------------------------------------------- configs, end to end
@pytest.mark.parametrize("experiment,n_experts", [("quick_varied", 2), ("table1_varied", 3)])
def test_varied_experiments_compose(experiment, n_experts):
    from hydra.utils import instantiate

    cfg = compose_train(f"experiment={experiment}")
    assert cfg.name == experiment and cfg.env.layout.n_experts == n_experts
    assert list(cfg.split) == [10, 20, 30, 40] and cfg.n_demonstrations == 100
    assert cfg.algo == compose_train("experiment=quick").algo  # quick's algorithm settings
    layout = instantiate(cfg.env.layout)
    assert layout.start_sets is not None and layout.n_experts == n_experts
    assert [list(r) for r in cfg.env.layout.start_regions][:n_experts] == \
        [list(r) for r in SCOBEE_START_REGIONS[n_experts]]
    assert layout == GridLayout.scobee_varied(n_experts)


def run_train(tmp_path, *overrides):
    out = train_cli(tmp_path, "env.model.horizon=8", "solver.compile=false",
                    "algo.outer_iterations=1", "algo.inner_steps=2", "eval_episodes=20",
                    "n_demonstrations=12", "split=[5,7]", "logger=none", *overrides)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    demos = np.load(tmp_path / "demos.npz")["states"]
    return res, demos


def check_run(res, demos, experiment, n_experts, regions):
    assert res["experiment"] == experiment
    starts = demos[:, 0]  # [m, N]
    assert starts.shape[1] == n_experts
    layout = GridLayout.scobee_varied(n_experts, start_regions=regions)
    for i, cells in enumerate(layout.start_cell_sets):
        assert set(starts[:, i].tolist()) <= set(cells)
    assert len({tuple(s) for s in starts.tolist()}) > 1  # not one fixed start
    for name in ("D-ICRL", "C-ICRL", "Experts (ground truth)"):
        for row in res["methods"][name]["learners"]:
            assert 0.0 <= row["CVR"] <= 1.0 and np.isfinite(row["CR_mean"])
    (experts,) = res["methods"]["Experts (ground truth)"]["learners"]
    assert experts["CVR"] == 0.0  # safe from every start


def test_quick_varied_runs_end_to_end(tmp_path):
    res, demos = run_train(tmp_path, "experiment=quick_varied")
    check_run(res, demos, "quick_varied", 2, SCOBEE_START_REGIONS[2])


@pytest.mark.slow  # ~20 s; the varied protocol end to end: quick_varied above
def test_table1_varied_runs_one_outer_iteration_at_reduced_scale(tmp_path):
    # Reduced scale: the first 2 of table1_varied's 3 experts (their blocks as in the
    # experiment), T = 8, one outer iteration, and greedy baselines that add no
    # constraint. The 3-expert problem (387M pairs) is experiment=table1_varied itself.
    res, demos = run_train(tmp_path, "experiment=table1_varied", "env.layout.n_experts=2",
                           "baselines.max_constraints=0")
    check_run(res, demos, "table1_varied", 2, SCOBEE_START_REGIONS[3][:2])
    assert list(res["methods"]) == ["D-ICRL", "C-ICRL", "ME-greedy", "MCE-greedy",
                                    "Experts (ground truth)", "Experts (nominal)"]
