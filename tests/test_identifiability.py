"""Identifiability of cost features (``dicrl_torch.algos.identifiability``) on tiny
layouts whose classes are derived by hand, and the probability of accruing a feature
against brute-force enumeration, a dense chain and Monte-Carlo sampling.

Tests 1–3 use deterministic moves (``p_success = 1``), optimal experts (temperature 0,
uniform ties) and hand-written demonstrations, so that the set ``U`` of undemonstrated
features and every shortest path can be read off the layout."""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest
import torch
from brute_force import joint_transition

from dicrl_torch.algos.identifiability import (
    Identifiability,
    accrual_probability,
    classify_features,
    fnr_required,
    joint_initial_distribution,
)
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import ACTION_NAMES, GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    FrozenModuleBasis,
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
    random_mlp,
)
from dicrl_torch.solvers.experts import sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

# brute_force builds its sparse transition without invariant checks (a torch warning)
pytestmark = pytest.mark.filterwarnings("ignore:Sparse invariant checks:UserWarning")


# ------------------------------------------------------------------ helpers
def problem(layout: GridLayout, horizon: int, p: float = 1.0):
    model = TabularGridModel(layout=layout, horizon=horizon, gamma=0.99, p_success=p)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    rb = GoalClosenessRewardBasis(model)
    return model, solver, rb().weighted(rb.true_weights())


def demos_of(model: TabularGridModel, *runs: list[list[str]]) -> Demonstrations:
    """Deterministic demonstrations from the start cells: ``runs`` is one list per
    trajectory of per-step lists of action names (one per expert)."""
    nxt = model.next_cell
    states, actions = [], []
    for run in runs:
        cells = list(model.start_state)
        s, a = [list(cells)], []
        for step in run:
            acts = [ACTION_NAMES.index(name) for name in step]
            cells = [int(nxt[c, k]) for c, k in zip(cells, acts, strict=True)]
            s.append(list(cells))
            a.append(acts)
        states.append(s)
        actions.append(a)
    return Demonstrations(states=np.array(states), actions=np.array(actions),
                          n_cells=model.n_cells, n_actions=model.n_actions)


def names(result: Identifiability, mask) -> set[str]:
    return set(result.names_of(mask))


def one_expert(actions: str) -> list[list[str]]:
    return [[a] for a in actions.split()]


# ------------------------------------------------------------------ 1. a hidden wall cell
def thick_wall():
    """4x4, one expert from (0,0) to (3,0); a wall two cells thick, (1,0) (2,0) (1,1)
    (2,1), open below. The optimal path goes under it in 5 moves; at the goal the expert
    stays by any action that keeps it there (stay, or a move off the grid such as NW)::

        S # # G        (0,0) S (0,1) SE (1,2) E (2,2) NE (3,1) N (3,0), NW, stay, stay
        . # # .
        . . . .
        . . . .
    """
    layout = GridLayout(size=4, starts=((0, 0),), goals=((3, 0),),
                        obstacles=((1, 0), (2, 0), (1, 1), (2, 1)))
    model, solver, reward = problem(layout, horizon=8)
    demos = demos_of(model, one_expert("S SE E NE N NW stay stay"))
    return model, solver, reward, demos


def test_a_wall_cell_behind_another_is_undetermined():
    """U holds the four wall cells, the unvisited cells and the actions W and SW.

    - (1,1) alone open (everything else in U forbidden): (0,0) SE (1,1) SE (2,2) NE (3,1)
      N (3,0), 4 moves instead of 5, with demonstrated actions: required, probability 1.
    - (2,1) alone open: (0,0) S (0,1) SE (1,2) NE (2,1) NE (3,0), 4 moves: required.
    - (1,0) alone open: its other neighbours are the wall, (0,0) (leaving by W) and (0,1)
      (by SW), both forbidden: a dead end, never entered. Undetermined.
    - (2,0) alone open: entered only from (3,0) (by W, forbidden) or from (3,1) (NW),
      and then E to the goal: a step longer than N from (3,1). Never taken.

    (Had the demonstration stayed at the goal by ``stay`` alone, NW would be required
    too: NW off the grid ties with ``stay`` there.)
    """
    model, solver, reward, demos = thick_wall()
    basis = SharedIndicatorCostBasis(model)
    result = classify_features(solver=solver, reward=reward, cost_basis=basis,
                               demonstrations=demos)
    assert result.n_features == basis.dim and not result.infeasible.any()
    # the classes partition the features
    total = (result.demonstrated.long() + result.required.long() + result.undetermined.long())
    assert bool((total == 1).all())
    assert names(result, result.demonstrated) == {
        "cell(0,0)", "cell(0,1)", "cell(1,2)", "cell(2,2)", "cell(3,1)", "cell(3,0)",
        "action S", "action SE", "action E", "action NE", "action N", "action NW",
        "action stay"}
    assert names(result, result.required) == {"cell(1,1)", "cell(2,1)"}
    p = dict(zip(result.names, result.probability.tolist(), strict=True))
    assert p["cell(1,1)"] == pytest.approx(1.0, abs=1e-12)
    assert p["cell(2,1)"] == pytest.approx(1.0, abs=1e-12)
    assert p["cell(1,0)"] == 0.0 and p["cell(2,0)"] == 0.0
    assert math.isnan(p["cell(0,0)"])  # demonstrated: not computed

    true = basis.true_constraints()
    wall = result.restrict(true)
    assert (wall.n_features, wall.n_demonstrated, wall.n_required, wall.n_undetermined) == \
        (4, 0, 2, 2)
    assert names(wall, wall.undetermined) == {"cell(1,0)", "cell(2,0)"}
    assert math.isnan(float(wall.probability[basis.names.index("cell(3,3)")]))
    # only= classifies the true constraints alone, with the same answer and 4 solves
    only = classify_features(solver=solver, reward=reward, cost_basis=basis,
                             demonstrations=demos, only=true)
    assert only.n_solves == 4 and names(only, only.required) == names(wall, wall.required)
    assert names(only, only.undetermined) == names(wall, wall.undetermined)
    # FNR over the required true constraints
    learned = torch.zeros(basis.dim, dtype=torch.bool)
    learned[basis.names.index("cell(1,1)")] = True
    learned[basis.names.index("cell(1,0)")] = True  # an undetermined one: no credit
    assert fnr_required(learned, true, result) == 0.5
    assert fnr_required(learned.numpy(), true.numpy(), only) == 0.5
    assert fnr_required(learned, None, result) is None
    d = result.as_dict()
    assert d["n_required"] == 2 and d["required"] == ["cell(1,1)", "cell(2,1)"]


def test_per_expert_and_region_bases():
    """Per-expert basis (one expert): the same classes, in expert 0's block. A region
    over the front of the wall, (1,1) and (2,1): its cells are also single features, so
    neither the region (its cells stay forbidden) nor a cell (the region stays
    forbidden) can ever be used alone: all three are undetermined — constraining the
    cells or the region explains the data equally."""
    model, solver, reward, demos = thick_wall()
    per = PerExpertIndicatorCostBasis(model)
    r = classify_features(solver=solver, reward=reward, cost_basis=per, demonstrations=demos)
    assert names(r, r.required) == {"expert0/cell(1,1)", "expert0/cell(2,1)"}
    regions = RegionIndicatorCostBasis(model, regions={"front": [(1, 1), (2, 1)]})
    r = classify_features(solver=solver, reward=reward, cost_basis=regions,
                          demonstrations=demos)
    assert r.n_required == 0
    assert {"region front", "cell(1,1)", "cell(2,1)"} <= names(r, r.undetermined)


# ------------------------------------------------------------------ 2. all required
def corridor():
    """3x3, one expert from (0,0) to (2,0), wall (1,0) (1,1)::

        S # G      (0,0) S (0,1) SE (1,2) NE (2,1) N (2,0), then at the goal E, NW, stay
        . # .      (moves off the grid: the expert stays), so E and NW are demonstrated.
        . . .
    """
    layout = GridLayout(size=3, starts=((0, 0),), goals=((2, 0),),
                        obstacles=((1, 0), (1, 1)))
    model, solver, reward = problem(layout, horizon=7)
    demos = demos_of(model, one_expert("S SE NE N E NW stay"))
    return model, solver, reward, demos


def test_every_obstacle_required():
    """(1,0) alone open: E, E reaches the goal in 2 moves instead of 4. (1,1) alone
    open: SE, NE. Both required with probability 1; the unvisited corner cells and the
    unused actions W, SW are undetermined."""
    model, solver, reward, demos = corridor()
    basis = SharedIndicatorCostBasis(model)
    result = classify_features(solver=solver, reward=reward, cost_basis=basis,
                               demonstrations=demos)
    assert names(result, result.required) == {"cell(1,0)", "cell(1,1)"}
    assert names(result, result.undetermined) == {"cell(0,2)", "cell(2,2)", "action W",
                                                  "action SW", "collision"}
    true = result.restrict(basis.true_constraints())
    assert (true.n_demonstrated, true.n_required, true.n_undetermined) == (0, 2, 0)
    assert torch.allclose(true.probability[true.required], torch.ones(2, dtype=torch.float64))


def test_collision_required_between_two_experts():
    """3x3 open grid; expert 1 from (0,1) to (2,1), expert 2 from (1,0) to (1,2); the
    only true constraint is the collision. Hand-written demonstrations avoid it: expert 1
    NE, SE while expert 2 goes S, S; expert 1 E, E while expert 2 goes SW, SE; and, at
    the last decision (t = T-1, where nothing more is scored, so the optimal experts pick
    any safe action), the pairs of final moves (S, NW), (N, W), (W, NE), (NW, E),
    (SW, N). Every action and every cell but (0,0) is demonstrated: U = {(0,0),
    collision}.

    Collision alone open: each expert reaches its goal in two moves through any of three
    middle cells (expert 1: (1,0) (1,1) (1,2); expert 2: (0,1) (1,1) (2,1)), all equally
    close to its goal: 9 tied joint moves, one of which meets in (1,1) (1/9). At the last
    decision all 9 x 9 joint actions tie; they meet with probability 10/81: in (1,1) or
    (2,2) (1/81 each), in (2,1) (expert 1 keeps its goal by one of 4 actions, expert 2
    NE: 4/81) or in (1,2) (4/81). In all 1/9 + 8/9 · 10/81 = 161/729. The per-expert
    basis leaves the same moves open."""
    layout = GridLayout(size=3, starts=((0, 1), (1, 0)), goals=((2, 1), (1, 2)))
    model, solver, reward = problem(layout, horizon=4)
    stay = [["stay", "stay"]] * 2
    runs = [[["NE", "S"], ["SE", "S"]] + stay, [["E", "SW"], ["E", "SE"]] + stay]
    runs += [[["NE", "S"], ["SE", "S"], ["stay", "stay"], last]
             for last in (["S", "NW"], ["N", "W"], ["W", "NE"], ["NW", "E"], ["SW", "N"])]
    demos = demos_of(model, *runs)
    for basis in (SharedIndicatorCostBasis(model), PerExpertIndicatorCostBasis(model)):
        result = classify_features(solver=solver, reward=reward, cost_basis=basis,
                                   demonstrations=demos)
        assert names(result, result.required) == {"collision"}
        assert float(result.probability[-1]) == pytest.approx(161 / 729, abs=1e-12)
        true = result.restrict(basis.true_constraints())
        assert (true.n_features, true.n_required) == (1, 1)
    assert names(result, result.undetermined) == {"expert0/cell(0,0)", "expert0/cell(0,2)",
                                                  "expert1/cell(0,0)", "expert1/cell(2,0)"}


# ------------------------------------------------------------------ 3. P0
def test_p0_mass_makes_a_feature_demonstrated():
    """The corridor with P0 = 1/2 at (0,0) and 1/2 at (0,2) (per expert, or joint), the
    demonstrations still all from (0,0): cell (0,2) is demonstrated by P0 alone (it is
    undetermined under the point mass). From (0,2), with (1,0) alone open, the two
    3-move paths N NE E (through (1,0)) and E NE N tie: (1,0) is used with probability
    1/2 + 1/2 · 1/2 = 3/4; (1,1) still with probability 1 (NE, NE from (0,2))."""
    model, solver, reward, demos = corridor()
    basis = SharedIndicatorCostBasis(model)
    point = classify_features(solver=solver, reward=reward, cost_basis=basis,
                              demonstrations=demos)
    start = basis.names.index("cell(0,0)")
    corner = basis.names.index("cell(0,2)")
    assert point.demonstrated[start] and point.undetermined[corner]
    per_expert = torch.zeros(1, 9, dtype=torch.float64)
    per_expert[0, model.layout.cell((0, 0))] = 0.5
    per_expert[0, model.layout.cell((0, 2))] = 0.5
    for p0 in (per_expert, per_expert[0]):  # [N, S1] and joint [S1] (one expert)
        result = classify_features(solver=solver, reward=reward, cost_basis=basis,
                                   demonstrations=demos, initial_distribution=p0)
        assert result.demonstrated[corner] and result.demonstrated[start]
        p = dict(zip(result.names, result.probability.tolist(), strict=True))
        assert p["cell(1,0)"] == pytest.approx(0.75, abs=1e-12)
        assert p["cell(1,1)"] == pytest.approx(1.0, abs=1e-12)
        assert names(result, result.required) == {"cell(1,0)", "cell(1,1)"}


def test_a_start_without_safe_moves_is_infeasible():
    """3x3 open grid, one expert from (0,0) to (2,0) along the top row: E, E, then NE
    (off the grid: it stays). Only E and NE and the top row are demonstrated. P0 puts
    half its mass on (0,2), where no demonstration started: from there E leads to (1,2)
    and NE to (1,1), both undemonstrated, so whether the expert has a safe move there
    depends on the one feature left open:

    - (1,1): NE, NE from (0,2) (E, E from (0,0)): required, probability 1/2;
    - an action that keeps it at (0,2) (stay, or S, W, SW, NW, SE off the grid): it
      waits there with it (probability 1/2); from (0,0) the expert reaches the goal at
      t = 2 and decides 3 more times there, uniformly among the moves that keep it at
      the goal (E, NE and the open one, if it does: stay, NW, SE) and, at the last
      decision, where nothing more is scored, among all safe moves (those and W, back
      to (1,0)). So stay, NW, SE: 1/2 + 1/2 (1 - (2/3)^3) = 23/27; W: 1/2 + 1/2 · 1/3;
      S, SW (into undemonstrated cells from the goal): 1/2. All required;
    - any other (the cells (0,1) (1,2) (2,1) (2,2), N, collision): (0,2) has no safe
      move, there is no hard-constrained model: infeasible, NaN, undetermined.
    """
    layout = GridLayout(size=3, starts=((0, 0),), goals=((2, 0),))
    model, solver, reward = problem(layout, horizon=5)
    demos = demos_of(model, one_expert("E E NE NE NE"))
    p0 = torch.zeros(9, dtype=torch.float64)
    p0[[layout.cell((0, 0)), layout.cell((0, 2))]] = 0.5
    result = classify_features(solver=solver, reward=reward,
                               cost_basis=SharedIndicatorCostBasis(model),
                               demonstrations=demos, initial_distribution=p0)
    assert names(result, result.demonstrated) == {
        "cell(0,0)", "cell(1,0)", "cell(2,0)", "cell(0,2)", "action E", "action NE"}
    waits = {f"action {a}" for a in ("stay", "S", "W", "SW", "NW", "SE")}
    assert names(result, result.required) == {"cell(1,1)"} | waits
    p = dict(zip(result.names, result.probability.tolist(), strict=True))
    want = {"cell(1,1)": 1 / 2, "action stay": 23 / 27, "action NW": 23 / 27,
            "action SE": 23 / 27, "action W": 2 / 3, "action S": 1 / 2, "action SW": 1 / 2}
    assert {n: p[n] for n in want} == pytest.approx(want, abs=1e-12)
    infeasible = {"cell(0,1)", "cell(1,2)", "cell(2,1)", "cell(2,2)", "action N", "collision"}
    assert names(result, result.infeasible) == infeasible
    assert names(result, result.undetermined) == infeasible
    assert result.probability[result.infeasible].isnan().all()


def test_p0_per_expert_is_the_product():
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=3)
    per = torch.zeros(2, 9, dtype=torch.float64)
    per[0, [0, 1]] = 0.5
    per[1, [4, 8]] = torch.tensor([0.25, 0.75], dtype=torch.float64)
    joint = joint_initial_distribution(model, per)
    assert joint.shape == (9, 9)
    assert joint[1, 8] == pytest.approx(0.375) and joint.sum() == pytest.approx(1.0)
    assert torch.equal(joint_initial_distribution(model), model.initial_distribution())


# ------------------------------------------------------------------ 4. the probability
def test_probability_against_trajectory_enumeration():
    """One expert, 3x3, slips (p = 0.8), T = 3: every trajectory (9 actions x 2 outcomes
    per step) enumerated with its probability; a trajectory accrues a cell when it stands
    there at t < T or ends there, an action when it takes it."""
    model = TabularGridModel(layout=GridLayout.open_grid(3, 1), horizon=3, gamma=0.9,
                             p_success=0.8)
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights())
    basis = SharedIndicatorCostBasis(model)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    nxt = model.next_cell
    s0 = model.start_state[0]
    for tau in (0.0, 1.0):
        sol = solver.solve(reward, temperature=tau, forward=False)
        pis = [sol.policy_dense(t) for t in range(3)]  # [S1, A1]
        for name in ("cell(1,1)", "cell(2,1)", "action E", "action SE"):
            j = basis.names.index(name)
            kind, what = name.split(" ") if name.startswith("action") else ("cell", name)
            want = 0.0
            for steps in itertools.product(range(9), (True, False), repeat=3):
                s, pr, hit = s0, 1.0, False
                for t, (a, moved) in enumerate(zip(steps[0::2], steps[1::2], strict=True)):
                    pr *= float(pis[t][s, a]) * (0.8 if moved else 0.2)
                    hit |= (basis.names[s] == what) if kind == "cell" else \
                        ACTION_NAMES[a] == what
                    s = int(nxt[s, a]) if moved else s
                hit |= kind == "cell" and basis.names[s] == what
                want += pr * hit
            got = accrual_probability(sol, basis, j)
            assert got == pytest.approx(want, abs=1e-12), (tau, name)


@functools.cache
def brute_P(size: int, n: int, p: float) -> torch.Tensor:
    return joint_transition(size, n, p).to_dense()


def dense_accrual(model, pis, phi_dense, state_feature, target, p0):
    """The killed chain on dense arrays: brute-force joint transition ``[S*A, S]``."""
    P = brute_P(model.layout.size, model.n_experts, model.p_success)
    S, A = pis[0].shape
    acc = (phi_dense[:, :, target] > 0).any(-1)  # [S, A]
    final = (phi_dense[:, 0, target & state_feature] > 0).any(-1)  # [S]
    d, removed = p0.reshape(-1).clone(), 0.0
    for pi in pis:
        rho = d.unsqueeze(1) * pi
        removed += float(rho[acc].sum())
        rho[acc] = 0.0
        d = rho.reshape(-1) @ P
    return removed + float(d[final].sum())


@pytest.mark.parametrize("tau", [0.0, 0.5])
def test_probability_against_dense_chain_two_experts(tau):
    """Two experts with slips, joint (collision), cell and action features, with and
    without a hard mask, against the killed chain computed densely."""
    from dicrl_torch.algos.greedy import constraint_masks, is_state_feature

    layout = GridLayout(size=3, starts=((0, 1), (1, 0)), goals=((2, 1), (1, 2)))
    model = TabularGridModel(layout=layout, horizon=5, gamma=0.95, p_success=0.8)
    rb = GoalClosenessRewardBasis(model)
    basis = SharedIndicatorCostBasis(model)
    phi = basis()
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    p0 = torch.full((9, 9), 1 / 81, dtype=torch.float64)  # a spread P0 as well
    for masked in ((), ("cell(1,1)",)):
        sel = torch.zeros(basis.dim, dtype=torch.bool)
        sel[[basis.names.index(n) for n in masked]] = True
        mask, terminal = constraint_masks(phi, sel, model)
        sol = solver.solve(rb().weighted(rb.true_weights()) + mask, temperature=tau,
                           forward=False, terminal_value=terminal)
        pis = [sol.policy_dense(t) for t in range(model.horizon)]
        for group in (["collision"], ["cell(1,2)"], ["action E"], ["collision", "action S"]):
            target = torch.zeros(basis.dim, dtype=torch.bool)
            target[[basis.names.index(n) for n in group]] = True
            for start in (None, p0):
                d0 = model.initial_distribution() if start is None else start
                want = dense_accrual(model, pis, phi.dense(), is_state_feature(phi), target, d0)
                got = accrual_probability(sol, phi, target, initial_distribution=start)
                assert got == pytest.approx(want, abs=1e-12), (masked, group)


def test_probability_against_monte_carlo():
    """Optimal experts with slips, the collision: the exact probability against the
    frequency over trajectories of ``sample_trajectories`` (the experts' sampler)."""
    layout = GridLayout(size=3, starts=((0, 1), (1, 0)), goals=((2, 1), (1, 2)))
    model, solver, reward = problem(layout, horizon=6, p=0.8)
    basis = SharedIndicatorCostBasis(model)
    sol = solver.solve(reward, temperature=0.0, forward=False)
    p = accrual_probability(sol, basis, basis.dim - 1)
    assert 0.05 < p < 0.95
    demos = sample_trajectories(sol, 4000, np.random.default_rng(0))
    hit = (demos.states[:, :, 0] == demos.states[:, :, 1]).any(1)
    assert abs(hit.mean() - p) < 4.5 * math.sqrt(p * (1 - p) / len(hit))


# ------------------------------------------------------------------ 5. bad input
def test_bad_input_names_the_fix():
    model, solver, reward, demos = corridor()
    basis = SharedIndicatorCostBasis(model)
    kw = dict(solver=solver, reward=reward, cost_basis=basis, demonstrations=demos)
    # a basis of another model: another grid, or the same grid with other constraints
    other = TabularGridModel(layout=GridLayout.open_grid(4, 1), horizon=7)
    with pytest.raises(ValueError, match="another model.*solver.model"):
        classify_features(**{**kw, "cost_basis": SharedIndicatorCostBasis(other)})
    moved = TabularGridModel(layout=GridLayout(size=3, starts=((0, 0),), goals=((2, 0),),
                                               obstacles=((1, 1),)), horizon=7)
    with pytest.raises(ValueError, match="another model"):
        classify_features(**{**kw, "cost_basis": SharedIndicatorCostBasis(moved)})
    # demonstrations of another grid: cells, experts, horizon
    wrong = [Demonstrations(states=np.zeros((2, 8, 1), np.int64),
                            actions=np.zeros((2, 7, 1), np.int64), n_cells=16, n_actions=9),
             Demonstrations(states=np.zeros((2, 8, 2), np.int64),
                            actions=np.zeros((2, 7, 2), np.int64), n_cells=9, n_actions=9),
             Demonstrations(states=np.zeros((2, 5, 1), np.int64),
                            actions=np.zeros((2, 4, 1), np.int64), n_cells=9, n_actions=9)]
    for bad in wrong:
        with pytest.raises(ValueError, match="Sample them from this model"):
            classify_features(**{**kw, "demonstrations": bad})
    with pytest.raises(ValueError, match="Sample them from this model"):
        classify_features(**{**kw, "demonstrations": [demos, wrong[0]]})
    # no demonstrations
    with pytest.raises(ValueError, match="No demonstrations"):
        classify_features(**{**kw, "demonstrations": []})
    # a basis positive everywhere
    mlp = FrozenModuleBasis(model, random_mlp(out_dim=4), out_dim=4)
    with pytest.raises(ValueError, match="positive on every state-action pair.*indicator"):
        classify_features(**{**kw, "cost_basis": mlp})
    # demonstrations starting where P0 has no mass
    elsewhere = torch.zeros(9, dtype=torch.float64)
    elsewhere[model.layout.cell((0, 2))] = 1.0
    with pytest.raises(ValueError, match="P0 has no mass.*initial_distribution"):
        classify_features(**kw, initial_distribution=elsewhere)
    for p0, msg in ((torch.ones(9), "sums to 9"), (torch.ones(2, 9) / 9, "shape"),
                    (-elsewhere, "non-negative")):
        with pytest.raises(ValueError, match=msg):
            classify_features(**kw, initial_distribution=p0)
    with pytest.raises(ValueError, match="only must be a \\[19\\] bool"):
        classify_features(**kw, only=torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="temperature"):
        classify_features(**kw, temperature=-1.0)
    # FNR_required needs the true constraints classified
    part = classify_features(**kw, only=torch.arange(basis.dim) == 0)
    with pytest.raises(ValueError, match="does not cover the true constraints"):
        fnr_required(basis.true_constraints(), basis.true_constraints(), part)
