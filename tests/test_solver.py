"""The factored solver against independent brute force on tiny instances."""

from __future__ import annotations

import functools
import math
import warnings

import numpy as np
import pytest
import torch
from brute_force import dense_solve, joint_transition, marginals
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dicrl_torch.envs.grid import DENSE_ENTRY_LIMIT, GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.solvers.experts import forbidden_state_value, hard_constraint_reward
from dicrl_torch.solvers.factored import FactoredSoftBellman

TOL = 1e-5
# (grid size, experts, layout): the tiny instances.
INSTANCES = [
    (3, 2, "open"),
    (4, 2, "open"),
    (3, 3, "open"),
    (9, 1, "scobee"),
]


def make_model(size: int, n: int, kind: str, horizon: int = 4, gamma: float = 0.9):
    layout = GridLayout.scobee(n) if kind == "scobee" else GridLayout.open_grid(size, n)
    return TabularGridModel(layout=layout, horizon=horizon, gamma=gamma)


@functools.cache
def brute_P(size: int, n: int, p: float = 0.8) -> torch.Tensor:
    return joint_transition(size, n, p)


def check_against_brute(model, reward, features, solver, temperature=1.0):
    S1, A1, N = model.n_cells, model.n_actions, model.n_experts
    P = brute_P(model.layout.size, N, model.p_success)
    p0 = model.initial_distribution().reshape(-1)
    V, pis, occ, occ_s = dense_solve(P, reward.dense(), p0, model.horizon, model.gamma,
                                     temperature)
    sol = solver.solve(reward, temperature=temperature)
    T = model.horizon
    assert (sol.V.reshape(T + 1, -1) - V).abs().max() < TOL
    for t in range(T):
        assert (sol.policy_dense(t) - pis[t]).abs().max() < TOL
    assert (sol.local_occupancy - marginals(occ, N, S1, A1)).abs().max() < TOL
    assert (sol.state_occupancy.reshape(-1) - occ_s).abs().max() < TOL
    for f in features:
        mu_dense = torch.einsum("sa,sal->l", occ, f.dense())
        assert (sol.feature_expectation(f) - mu_dense).abs().max() < TOL


weights = st.floats(-2.0, 2.0, allow_nan=False)
unit = st.floats(0.0, 1.0, allow_nan=False)
lam = st.floats(-10.0, 10.0, allow_nan=False)


@pytest.mark.parametrize("size,n,kind", INSTANCES)
@pytest.mark.parametrize("cost_basis", [SharedIndicatorCostBasis, PerExpertIndicatorCostBasis])
@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_factored_matches_brute_force(size, n, kind, cost_basis, data):
    model = make_model(size, n, kind)
    rb, cb = GoalClosenessRewardBasis(model), cost_basis(model)
    fr, fc = rb(), cb()
    w_r = torch.tensor(data.draw(st.lists(weights, min_size=fr.dim, max_size=fr.dim)),
                       dtype=torch.float64)
    w_c = torch.tensor(data.draw(st.lists(unit, min_size=fc.dim, max_size=fc.dim)),
                       dtype=torch.float64)
    reward = fr.weighted(w_r) + fc.weighted(w_c).scale(data.draw(lam))
    solver = FactoredSoftBellman(model=model, dtype=torch.float64, compile=False, chunk_cells=2)
    check_against_brute(model, reward, [fr, fc], solver)


def test_compiled_kernels_match_brute_force():
    model = make_model(3, 2, "open")
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    g = torch.Generator().manual_seed(1)
    reward = rb().weighted(torch.randn(rb.dim, generator=g, dtype=torch.float64)) + cb().weighted(
        torch.rand(cb.dim, generator=g, dtype=torch.float64)).scale(-4.0)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64, compile=True)
    check_against_brute(model, reward, [rb(), cb()], solver)


@pytest.mark.parametrize("temperature", [0.5, 2.0])
def test_temperature_matches_brute_force(temperature):
    model = make_model(3, 2, "open")
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights())
    solver = FactoredSoftBellman(model=model, dtype=torch.float64, compile=False)
    check_against_brute(model, reward, [rb()], solver, temperature=temperature)


def masked_game(horizon: int, gamma: float, scale: float = 1.0):
    """``(layout, model, reward)`` of a 3x3 two-expert grid with an obstacle in the centre
    and NE forbidden: the true reward (times ``scale``) plus the hard-constraint mask."""
    layout = GridLayout(size=3, starts=((0, 2), (2, 0)), goals=((2, 2), (0, 0)),
                        obstacles=((1, 1),), forbidden_actions=("NE",))
    model = TabularGridModel(layout=layout, horizon=horizon, gamma=gamma)
    rb = GoalClosenessRewardBasis(model)
    reward = (rb().weighted(rb.true_weights()).scale(scale)
              + hard_constraint_reward(model, layout))
    return layout, model, reward


def test_hard_max_dp_with_masks_matches_brute_force():
    layout, model, reward = masked_game(horizon=4, gamma=0.9)
    terminal = forbidden_state_value(model, layout)
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        reward, temperature=0.0, forward=False, terminal_value=terminal)
    P = brute_P(3, 2)
    V, pis, _, _ = dense_solve(P, reward.dense(), model.initial_distribution().reshape(-1),
                               4, 0.9, temperature=0.0, terminal=terminal)
    assert torch.isinf(V[4]).any()  # the terminal mask is in play
    finite = torch.isfinite(V)
    assert torch.equal(torch.isfinite(sol.V.reshape(5, -1)), finite)
    assert (sol.V.reshape(5, -1)[finite] - V[finite]).abs().max() < TOL
    # the policy at reachable (finite-value) states
    for t in range(4):
        ok = torch.isfinite(V[t])
        assert (sol.policy_dense(t)[ok] - pis[t][ok]).abs().max() < TOL


def test_soft_solver_with_masks_keeps_forbidden_mass_zero():
    layout, model, reward = masked_game(horizon=5, gamma=0.95)
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(reward)
    occ = sol.local_occupancy
    center = layout.cell((1, 1))
    assert occ[:, center].sum() < 1e-200  # tiny floor of the denormal-free exp, no more
    assert occ[:, :, 5].sum() < 1e-200  # NE
    assert abs(float(sol.state_occupancy.sum()) - sum(0.95**t for t in range(5))) < 1e-9


def test_float32_solver_close_to_float64():
    model = make_model(4, 2, "open", horizon=8, gamma=0.99)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    reward = rb().weighted(rb.true_weights()) + cb().weighted(
        torch.full((cb.dim,), 0.3, dtype=torch.float64)).scale(-3.0)
    s64 = FactoredSoftBellman(model=model, dtype=torch.float64).solve(reward)
    s32 = FactoredSoftBellman(model=model, dtype=torch.float32).solve(reward)
    assert (s32.V.double() - s64.V).abs().max() < 1e-4
    assert (s32.local_occupancy - s64.local_occupancy).abs().max() < 1e-5


@pytest.mark.parametrize("backup", ["causal", "trajectory"])
def test_float32_keeps_what_the_states_share_out_of_the_values(backup):
    """A part of V_t common to all states (here past the float32 limit of 1e4) leaves the
    policy as it is; the solver keeps it in the per-step baseline c_t, so float32 resolves
    the values at the scale of their spread over the states, and does not warn."""
    model = make_model(4, 2, "open", horizon=40, gamma=0.99)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    reward = rb().weighted(rb.true_weights()) + cb().weighted(
        torch.full((cb.dim,), 0.3, dtype=torch.float64)).scale(-3.0)
    solver = FactoredSoftBellman(model=model, dtype=torch.float32)
    plain = solver.solve(reward, backup=backup)
    exact = FactoredSoftBellman(model=model, dtype=torch.float64).solve(reward, backup=backup)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        # A constant terminal value: the same game, to the last bit.
        far = solver.solve(reward, backup=backup,
                           terminal_value=torch.full(model.state_shape, 2e4))
        # A constant reward: the same policy; float32 now resolves Q_t at the scale of
        # the reward (400 a step) instead of the values'.
        shifted = solver.solve(type(reward)(local=reward.local + 200.0, joint=reward.joint),
                               backup=backup)
    assert float(far.V.abs().min()) > 1e4 and float(shifted.V.abs().max()) > 1e4
    assert torch.equal(far.values, plain.values)
    assert torch.equal(far.local_occupancy, plain.local_occupancy)
    assert float(shifted.values.abs().max()) < 100.0
    assert (shifted.local_occupancy - exact.local_occupancy).abs().max() < 3e-3
    cells = torch.tensor([[0, 15], [5, 10], [3, 12]])
    for t in (0, 20, 39):
        assert (shifted.policy_at(t, cells) - exact.policy_at(t, cells)).abs().max() < 1e-4
    common = sum(400.0 * model.gamma**k for k in range(40))  # Σ_t γ^t · 2 · 200
    assert math.isclose(shifted.log_partition - exact.log_partition, common, rel_tol=1e-6)


@pytest.mark.parametrize("lam_", [1e6, -1e6])
def test_extreme_multipliers_stay_finite(lam_):
    model = make_model(4, 2, "open", horizon=6)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    reward = rb().weighted(rb.true_weights() * 1e3) + cb().weighted(
        torch.full((cb.dim,), 0.5, dtype=torch.float64)).scale(lam_)
    # float32 resolves |V| ~ 1e6 only to ~0.06: finite, but it warns to use float64.
    solver32 = FactoredSoftBellman(model=model, dtype=torch.float32)
    with pytest.warns(RuntimeWarning, match="float64"):
        sol32 = solver32.solve(reward)
    with warnings.catch_warnings():  # the same scale again: said once per solver
        warnings.simplefilter("error")
        solver32.solve(reward)
    with pytest.warns(RuntimeWarning, match="float64"):  # |V| doubled: said again
        solver32.solve(reward.scale(4.0))
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(reward)
    for s in (sol32, sol):
        assert torch.isfinite(s.V).all()
        assert torch.isfinite(s.local_occupancy).all()
        assert torch.isfinite(s.state_occupancy).all()
        assert torch.isfinite(s.policy_dense(0)).all()
    total = float(sol.state_occupancy.sum())
    assert math.isclose(total, sum(0.9**t for t in range(6)), rel_tol=1e-9)


def test_dense_transition_matches_enumeration_and_refuses_large():
    model = make_model(3, 2, "open")
    dense = model.dense_transition().reshape(-1, model.n_states)
    assert torch.allclose(dense, brute_P(3, 2).to_dense())
    with pytest.raises(ValueError, match="dense transition"):
        TabularGridModel(layout=GridLayout.scobee(2)).dense_transition()
    assert DENSE_ENTRY_LIMIT < 531441 * 81 * 81 * 81


def test_q_values_at_matches_dense():
    model = make_model(3, 2, "open")
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights())
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(reward, forward=False)
    P = brute_P(3, 2)
    EV = torch.sparse.mm(P, sol.V[2].reshape(-1, 1)).reshape(model.n_states, -1)
    Q = reward.dense() + model.gamma * EV
    cells = torch.tensor([[0, 8], [4, 4], [2, 6]])
    idx = cells[:, 0] * 9 + cells[:, 1]
    assert (sol.q_values_at(1, cells) - Q[idx]).abs().max() < 1e-10


def test_bad_inputs_are_refused():
    model = make_model(3, 2, "open")
    rb = GoalClosenessRewardBasis(model)
    good = rb().weighted(rb.true_weights())
    solver = FactoredSoftBellman(model=model)
    with pytest.raises(ValueError, match="NaN"):
        solver.solve(type(good)(local=good.local * np.nan))
    with pytest.raises(ValueError, match="reward.local must be"):
        solver.solve(type(good)(local=good.local[:1]))
    with pytest.raises(ValueError, match="temperature"):
        solver.solve(good, temperature=-1.0)
    with pytest.raises(ValueError, match="forward pass needs a soft policy"):
        solver.solve(good, temperature=0.0)
    with pytest.raises(ValueError, match="compile"):
        FactoredSoftBellman(model=model, compile="yes")
    with pytest.raises(ValueError, match="dtype"):
        FactoredSoftBellman(model=model, dtype=torch.int32)


@pytest.mark.parametrize("scale", [1.0, 1e5])
def test_float32_scale_warning_reads_the_finite_values(scale):
    """Forbidden states hold V = -inf; the float32 scale check looks past them and warns
    with the largest finite |V_t - c_t| (the values about their per-step baseline, what
    float32 must resolve), exactly when that passes the limit."""
    layout, model, reward = masked_game(horizon=4, gamma=0.9, scale=scale)
    terminal = forbidden_state_value(model, layout)
    solver = FactoredSoftBellman(model=model, dtype=torch.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = solver.solve(reward, forward=False, terminal_value=terminal)
    assert torch.isneginf(sol.V).any() and torch.equal(sol.V.isneginf(), sol.values.isneginf())
    finite_max = float(sol.values[torch.isfinite(sol.values)].abs().max())
    said = [str(w.message) for w in caught if "float32" in str(w.message)]
    if scale == 1.0:
        assert finite_max < 1e4 and not said
    else:
        assert finite_max > 1e4 and len(said) == 1
        assert said[0].startswith(f"|V_t - c_t| reaches {finite_max:.3g} ")
