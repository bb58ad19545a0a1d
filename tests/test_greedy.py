"""The trajectory (ME) backup of the factored solver against brute force, and the greedy
constraint inference (ME-greedy, MCE-greedy) of ``dicrl_torch.algos.greedy``."""

from __future__ import annotations

import dataclasses
import functools
import io
import itertools
import math
import time

import numpy as np
import pytest
import torch
from brute_force import discounted_occupancy, joint_transition, marginals

from dicrl_torch.algos.greedy import (
    GreedyConstraintInference,
    constraint_masks,
    demonstrated_features,
    mce_greedy,
    me_greedy,
    reachable_constraints,
    trajectory_log_likelihood,
)
from dicrl_torch.algos.icrl import log_likelihood
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    FactoredFeatures,
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.metrics import false_positive_rate, rollout_true_cmg
from dicrl_torch.solvers.experts import (
    expert_solution,
    forbidden_state_value,
    hard_constraint_reward,
    sample_trajectories,
)
from dicrl_torch.solvers.factored import FactoredSoftBellman

TOL = 1e-9


@functools.cache
def brute_P(size: int, n: int, p: float) -> torch.Tensor:
    return joint_transition(size, n, p).to_dense()


def dense_me(P, r, p0, T, gamma, tau=1.0, terminal=None):
    """Dense trajectory-level ME model, straight from its definition (float64).

    ``L = τ log E[exp(V'/τ)]``, ``Q = r + γL``; the forward pass pushes ``ρ = d π``
    through the tilted dynamics ``P exp((V' - L)/τ)`` from ``d_0 ∝ P0 exp(V_0/τ)``.

    Returns V ``[T+1, S]``, policies and L ``[T, S, A]``, occupancy ``[S, A]``, state
    occupancy ``[S]``.
    """
    S, A = r.shape
    V = torch.zeros(T + 1, S, dtype=torch.float64)
    if terminal is not None:
        V[T] = terminal.reshape(S)
    L = torch.zeros(T, S, A, dtype=torch.float64)
    pis = torch.zeros(T, S, A, dtype=torch.float64)
    for t in range(T - 1, -1, -1):
        vn = V[t + 1] / tau
        top = vn[torch.isfinite(vn)].max()  # one global shift: values are small here
        L[t] = (tau * (torch.log(P @ torch.exp(vn - top)) + top)).reshape(S, A)
        Q = r + gamma * L[t]
        V[t] = tau * torch.logsumexp(Q / tau, 1)
        pis[t] = torch.nan_to_num(torch.softmax(Q / tau, 1))  # all-forbidden rows: 0
    w0 = p0 * torch.exp((V[0] - V[0][p0 > 0].max()) / tau)

    def push(t, rho):  # through the tilted dynamics
        lt = L[t].reshape(-1, 1)
        tilt = torch.where(torch.isfinite(lt), torch.exp((V[t + 1].unsqueeze(0) - lt) / tau), 0.0)
        return rho.reshape(-1) @ torch.nan_to_num(P * tilt)

    occ, occ_s = discounted_occupancy(w0 / w0.sum(), pis, gamma, push)
    return V, pis, L, occ, occ_s


def random_reward(model, seed=0, lam=-3.0):
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    g = torch.Generator().manual_seed(seed)
    return (rb().weighted(2 * torch.randn(rb.dim, generator=g, dtype=torch.float64))
            + cb().weighted(torch.rand(cb.dim, generator=g, dtype=torch.float64)).scale(lam))


def check_me_against_dense(model, reward, solver, tau=1.0, terminal=None, tol=TOL):
    N, T = model.n_experts, model.horizon
    P = brute_P(model.layout.size, N, model.p_success)
    p0 = model.initial_distribution().reshape(-1)
    V, pis, _, occ, occ_s = dense_me(P, reward.dense(), p0, T, model.gamma, tau, terminal)
    sol = solver.solve(reward, temperature=tau, backup="trajectory", terminal_value=terminal)
    got = sol.V.reshape(T + 1, -1).double()
    assert torch.equal(torch.isfinite(got), torch.isfinite(V))
    fin = torch.isfinite(V)
    assert (got[fin] - V[fin]).abs().max() < tol * 10
    for t in range(T):
        ok = torch.isfinite(V[t])
        assert (sol.policy_dense(t)[ok] - pis[t][ok]).abs().max() < tol
    assert (sol.local_occupancy - marginals(occ, N, model.n_cells, model.n_actions)
            ).abs().max() < tol
    assert (sol.state_occupancy.reshape(-1) - occ_s).abs().max() < tol
    for basis in (GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)):
        f = basis()
        mu = torch.einsum("sa,sal->l", occ, f.dense())
        assert (sol.feature_expectation(f) - mu).abs().max() < tol * 10
    log_z = tau * float(torch.logsumexp(torch.log(p0) + V[0] / tau, 0))
    assert abs(sol.log_partition - log_z) < tol * 10
    return sol


# --------------------------------------------------------------- the trajectory backup
@pytest.mark.parametrize("size,n,p,tau", [
    (3, 1, 0.8, 1.0),
    (3, 2, 0.8, 1.0),
    (3, 2, 0.8, 0.5),
    (2, 3, 0.7, 1.0),  # three experts: the middle expert's tilted pull
    (3, 2, 1.0, 1.0),  # deterministic: (1 - p) terms vanish
])
def test_trajectory_backup_matches_dense_definition(size, n, p, tau):
    model = TabularGridModel(layout=GridLayout.open_grid(size, n), horizon=4, gamma=0.9,
                             p_success=p)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64, chunk_cells=2)
    check_me_against_dense(model, random_reward(model), solver, tau)


def masked_layout():
    return GridLayout(size=3, starts=((0, 2), (2, 0)), goals=((2, 2), (0, 0)),
                      obstacles=((1, 1),), forbidden_actions=("NE",))


@pytest.mark.parametrize("p", [0.8, 1.0])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, TOL), (torch.float32, 2e-5)])
def test_trajectory_backup_with_hard_masks(p, dtype, tol):
    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=5, gamma=0.95, p_success=p)
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights()) + hard_constraint_reward(model, layout)
    terminal = forbidden_state_value(model, layout)
    sol = check_me_against_dense(model, reward, FactoredSoftBellman(model=model, dtype=dtype),
                                 terminal=terminal, tol=tol)
    center = layout.cell((1, 1))
    assert sol.local_occupancy[:, center].sum() < 1e-30  # the exp floor, no more
    assert not torch.isnan(sol.local_occupancy).any()


def test_trajectory_backup_is_ziebart_at_gamma_one():
    """At γ = 1 the model is P(ζ) ∝ P0 Π P exp(Σ r): check log Z, the occupancies and
    the log-likelihood against an enumeration of every trajectory."""
    model = TabularGridModel(layout=GridLayout.open_grid(3, 1), horizon=3, gamma=1.0,
                             p_success=0.8)
    reward = random_reward(model, seed=3)
    r = reward.local[0]  # [S1, A1]
    nxt = model.next_cell
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        reward, backup="trajectory")
    paths, weights = [], []
    s0 = model.start_state[0]
    for steps in itertools.product(range(9), (True, False), repeat=3):
        s, logw, states, acts = s0, 0.0, [s0], []
        for a, moved in zip(steps[0::2], steps[1::2], strict=True):
            logw += float(r[s, a]) + math.log(0.8 if moved else 0.2)
            s = int(nxt[s, a]) if moved else s
            states.append(s)
            acts.append(a)
        paths.append((states, acts))
        weights.append(logw)
    logw = torch.tensor(weights, dtype=torch.float64)
    log_z = float(torch.logsumexp(logw, 0))
    assert abs(sol.log_partition - log_z) < 1e-10
    prob = torch.exp(logw - log_z)
    occ = torch.zeros(9, 9, dtype=torch.float64)
    for (states, acts), pr in zip(paths, prob, strict=True):
        for s, a in zip(states[:-1], acts, strict=True):
            occ[s, a] += pr
    assert (sol.local_occupancy[0] - occ).abs().max() < 1e-12
    # log P(ζ) minus its dynamics terms Σ ln P, for a few trajectories
    picks = [0, 17, 1234, 5000]
    states = np.array([[paths[k][0]] for k in picks]).transpose(0, 2, 1)
    acts = np.array([[paths[k][1]] for k in picks]).transpose(0, 2, 1)
    demos = Demonstrations(states=states, actions=acts, n_cells=9, n_actions=9)
    want = sum(float(r[torch.tensor(paths[k][0][:-1]), torch.tensor(paths[k][1])].sum())
               - log_z for k in picks)
    assert abs(trajectory_log_likelihood(sol, demos) - want) < 1e-10


def test_trajectory_log_likelihood_matches_per_step_definition():
    """Discounted, stochastic: the telescoped likelihood equals the step-by-step sum
    ``Σ_t γ^t ln π_t + γ^{t+1} ln(P̃_t / P)`` over the model's conditionals."""
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=4, gamma=0.9,
                             p_success=0.8)
    reward = random_reward(model, seed=5)
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        reward, backup="trajectory")
    P = brute_P(3, 2, 0.8)
    V, pis, L, _, _ = dense_me(P, reward.dense(), model.initial_distribution().reshape(-1),
                               4, 0.9)
    demos = sample_trajectories(sol, 20, np.random.default_rng(0))
    s = torch.tensor(demos.states[..., 0] * 9 + demos.states[..., 1])  # [m, T+1]
    a = torch.tensor(demos.actions[..., 0] * 9 + demos.actions[..., 1])  # [m, T]
    want = 0.0
    for t in range(4):
        st, at, sn = s[:, t], a[:, t], s[:, t + 1]
        want += float((0.9**t * torch.log(pis[t][st, at])
                       + 0.9 ** (t + 1) * (V[t + 1][sn] - L[t][st, at])).sum())
    assert abs(trajectory_log_likelihood(sol, demos) - want) < 1e-9


def test_deterministic_dynamics_models_coincide():
    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=5, gamma=0.95, p_success=1.0)
    reward = random_reward(model, seed=1) + hard_constraint_reward(model, layout)
    terminal = forbidden_state_value(model, layout)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    me = solver.solve(reward, backup="trajectory", terminal_value=terminal)
    mce = solver.solve(reward, backup="causal", terminal_value=terminal)
    fin = torch.isfinite(mce.V)
    assert torch.equal(torch.isfinite(me.V), fin)
    assert (me.V[fin] - mce.V[fin]).abs().max() < 1e-12
    assert (me.local_occupancy - mce.local_occupancy).abs().max() < 1e-12
    assert (me.state_occupancy - mce.state_occupancy).abs().max() < 1e-12
    assert abs(me.log_partition - mce.log_partition) < 1e-12
    demos = sample_trajectories(mce, 30, np.random.default_rng(2))
    assert abs(trajectory_log_likelihood(me, demos) - log_likelihood(mce, demos)) < 1e-9
    # ... but not for stochastic dynamics
    model8 = TabularGridModel(layout=layout, horizon=5, gamma=0.95, p_success=0.8)
    s8 = FactoredSoftBellman(model=model8, dtype=torch.float64)
    r8 = random_reward(model8, seed=1)
    assert (s8.solve(r8, backup="trajectory").V - s8.solve(r8).V).abs().max() > 0.1


def test_deterministic_hard_max_dp_with_masks_matches_brute_force():
    """p_success = 1 with -inf masks: (1 - p) · (-inf) must not turn values into NaN
    (the experts of a deterministic game are solved this way)."""
    from brute_force import dense_solve

    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=4, gamma=0.9, p_success=1.0)
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights()) + hard_constraint_reward(model, layout)
    terminal = forbidden_state_value(model, layout)
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        reward, temperature=0.0, forward=False, terminal_value=terminal)
    V, pis, _, _ = dense_solve(joint_transition(3, 2, 1.0), reward.dense(),
                               model.initial_distribution().reshape(-1), 4, 0.9,
                               temperature=0.0, terminal=terminal)
    got = sol.V.reshape(5, -1)
    assert not torch.isnan(got).any()
    fin = torch.isfinite(V)
    assert torch.equal(torch.isfinite(got), fin) and (got[fin] - V[fin]).abs().max() < 1e-12
    for t in range(4):
        ok = torch.isfinite(V[t])
        assert (sol.policy_dense(t)[ok] - pis[t][ok]).abs().max() < 1e-12
    expert_solution(solver=FactoredSoftBellman(model=model), reward_features=rb(),
                    reward_weights=rb.true_weights())  # raised "cannot avoid" before


def test_policy_is_uniform_where_every_action_is_forbidden():
    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=3, gamma=0.9, p_success=0.8)
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights()) + hard_constraint_reward(model, layout)
    sol = FactoredSoftBellman(model=model, dtype=torch.float64).solve(
        reward, backup="trajectory", terminal_value=forbidden_state_value(model, layout))
    center = layout.cell((1, 1))
    pi = sol.policy_at(0, torch.tensor([[center, 0], [0, 8]]))
    assert torch.allclose(pi[0], torch.full((81,), 1 / 81, dtype=torch.float64))
    assert torch.isfinite(pi).all() and abs(float(pi[1].sum()) - 1) < 1e-12


def test_trajectory_backup_refuses_bad_arguments():
    model = TabularGridModel(layout=GridLayout.open_grid(3, 1), horizon=3)
    solver = FactoredSoftBellman(model=model)
    reward = random_reward(model)
    with pytest.raises(ValueError, match="backup must be"):
        solver.solve(reward, backup="forward")
    with pytest.raises(ValueError, match="temperature > 0"):
        solver.solve(reward, backup="trajectory", temperature=0.0, forward=False)
    with pytest.raises(ValueError, match="backup='trajectory'"):
        trajectory_log_likelihood(solver.solve(reward), sample_trajectories(
            solver.solve(reward), 2, np.random.default_rng(0)))


@pytest.mark.slow
def test_compiled_trajectory_kernels_match_dense():
    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=5, gamma=0.95, p_success=0.8)
    rb = GoalClosenessRewardBasis(model)
    reward = rb().weighted(rb.true_weights()) + hard_constraint_reward(model, layout)
    check_me_against_dense(model, reward, FactoredSoftBellman(
        model=model, dtype=torch.float64, compile=True),
        terminal=forbidden_state_value(model, layout))


# ------------------------------------------------------------------------ the greedy
@pytest.mark.parametrize("basis", [SharedIndicatorCostBasis, PerExpertIndicatorCostBasis])
def test_constraint_masks_of_the_true_set_are_the_experts_masks(basis):
    layout = masked_layout()
    model = TabularGridModel(layout=layout, horizon=4)
    cb = basis(model)
    mask, terminal = constraint_masks(cb(), cb.true_constraints(), model)
    want = hard_constraint_reward(model, layout)
    assert torch.equal(mask.local, want.local)
    assert torch.equal(mask.joint, want.joint)
    assert torch.equal(terminal, forbidden_state_value(model, layout))
    actions_only = cb.true_constraints() & torch.tensor(["action" in n for n in cb.names])
    assert constraint_masks(cb(), actions_only, model)[1] is None  # no state feature


def identifiable_problem(p_success: float, n_demos: int = 100):
    """5x5, one expert along the bottom row, one obstacle on its straight path (the
    detour over it costs nothing with diagonal moves, so no cell before it is a dead
    end) and SW forbidden (at the goal corner SW means staying): both constraints are
    identifiable from optimal demonstrations."""
    layout = GridLayout(size=5, starts=((0, 4),), goals=((4, 4),), obstacles=((2, 4),),
                        forbidden_actions=("SW",))
    model = TabularGridModel(layout=layout, horizon=12, gamma=0.99, p_success=p_success)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    experts = expert_solution(solver=solver, reward_features=rb(),
                              reward_weights=rb.true_weights())
    demos = sample_trajectories(experts, n_demos, np.random.default_rng(0))
    return layout, model, solver, cb, rb().weighted(rb.true_weights()), demos


@pytest.mark.parametrize("p_success", [1.0, 0.8])
@pytest.mark.parametrize("run", [me_greedy, mce_greedy])
def test_greedy_recovers_identifiable_constraints(p_success, run):
    layout, model, solver, cb, reward, demos = identifiable_problem(p_success)
    true = cb.true_constraints()
    res = run(solver=solver, reward=reward, cost_basis=cb, demonstrations=demos, epsilon=0.05)
    assert torch.equal(res.constraint_mask, true), res.added_names
    assert torch.equal(reachable_constraints(solver=solver, reward=reward, cost_basis=cb,
                                             true_mask=true), true)
    # bookkeeping: histories line up, every accepted gain passed ε, the last one did not
    k = len(res.added)
    assert len(res.log_likelihood) == k + 1 and len(res.improvement) == k
    assert np.allclose(np.diff(res.log_likelihood), res.improvement)
    assert all(g >= 0.05 for g in res.improvement)
    assert not res.steps[-1].accepted and res.steps[-1].improvement < 0.05
    assert res.added_names == [cb.names[j] for j in res.added]
    assert not (res.constraint_mask & demonstrated_features(cb(), demos, model.gamma)).any()
    assert math.isfinite(res.log_likelihood[-1])
    # the final policy rolls out in the true CMG and respects what it learned
    ev = rollout_true_cmg(policy=res.solution.policy_at, model=model, layout=layout,
                          reward_table=reward.local[:, :, 0], n_episodes=50,
                          rng=torch.Generator().manual_seed(0))
    assert ev.cvr <= 0.1


def test_greedy_models_coincide_for_deterministic_dynamics():
    _, _, solver, cb, reward, demos = identifiable_problem(1.0)
    kw = dict(solver=solver, reward=reward, cost_basis=cb, demonstrations=demos,
              epsilon=0.0, max_constraints=6)
    me, mce = me_greedy(**kw), mce_greedy(**kw)
    assert me.added == mce.added and len(me.added) == 6
    assert np.allclose(me.log_likelihood, mce.log_likelihood, atol=1e-9)


def slipped_problem() -> tuple[dict, SharedIndicatorCostBasis]:
    """3x3, 20% slip, one demonstration that tried N at (0,2) and slipped: the greedy's
    keyword arguments (ε = 0) and the cost basis."""
    model = TabularGridModel(layout=GridLayout.open_grid(3, 1), horizon=3, p_success=0.8)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    N_, E_ = 1, 3  # action indices of N and E
    demos = Demonstrations(states=np.array([[[6], [6], [7], [8]]]),
                           actions=np.array([[[N_], [E_], [E_]]]), n_cells=9, n_actions=9)
    return dict(solver=FactoredSoftBellman(model=model, dtype=torch.float64),
                reward=rb().weighted(rb.true_weights()), cost_basis=cb, demonstrations=demos,
                epsilon=0.0), cb


def test_mce_skips_a_candidate_a_slipped_demonstration_contradicts():
    """Under the MCE model with a hard mask on (0,1) the slipped demonstration's N at
    (0,2) is impossible (it risks entering), so (0,1) is infeasible; the ME model's
    optimistic dynamics allow it."""
    kw, cb = slipped_problem()
    target = cb.names.index("cell(0,1)")
    results = {}
    for kind in ("mce", "me"):
        g = GreedyConstraintInference(**kw, model=kind)
        assert g.candidates[target]
        only = torch.zeros(cb.dim, dtype=torch.bool)
        only[target] = True
        results[kind] = (g.mean_log_likelihood(g.solve(only)[0]), g.run())
    ll_mce, res_mce = results["mce"]
    assert ll_mce == -math.inf
    bad = [s for s in res_mce.steps if s.feature == target]
    assert len(bad) == 1 and bad[0].infeasible and not res_mce.constraint_mask[target]
    assert res_mce.steps[-1].feature != target  # it went on after skipping it
    ll_me, res_me = results["me"]
    assert math.isfinite(ll_me) and res_me.constraint_mask[target]


def scobee_single_expert(cost_basis_class, *, temperature):
    """The paper's layout with one expert (Scobee's setting), 20% slip, and 100
    demonstrations of the true CMG's expert at `temperature` (0: optimal)."""
    model = TabularGridModel(layout=GridLayout.scobee(1), horizon=40, gamma=0.99,
                             p_success=0.8)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    rb, cb = GoalClosenessRewardBasis(model), cost_basis_class(model)
    reward = rb().weighted(rb.true_weights())
    demos = sample_trajectories(expert_solution(solver=solver, reward_features=rb(),
                                                reward_weights=rb.true_weights(),
                                                temperature=temperature),
                                100, np.random.default_rng(0))
    return solver, cb, reward, demos


def test_scobee_single_expert_prefers_a_false_wall_the_likelihood_cannot_tell_apart():
    """The paper's layout, one expert (Scobee's setting), 20% slip: the cells x = 2,
    y = 4..8 form a dead-end pocket for the constrained expert, so a wall there explains
    the demonstrations as well as the true obstacles at x = 4 — better, in likelihood,
    than the true constraint set. The greedy meets the pocket first and learns it."""
    solver, cb, reward, demos = scobee_single_expert(SharedIndicatorCostBasis, temperature=0.0)
    true = cb.true_constraints()
    reach = reachable_constraints(solver=solver, reward=reward, cost_basis=cb, true_mask=true)
    assert [cb.names[j] for j in torch.nonzero(reach).flatten()] == [
        "cell(4,5)", "cell(4,6)", "cell(4,7)", "cell(4,8)", "action NE", "action NW"]
    for kind in ("me", "mce"):
        g = GreedyConstraintInference(solver=solver, reward=reward, cost_basis=cb,
                                      demonstrations=demos, model=kind)
        res = g.run()
        names = res.added_names
        assert names[0] == "action NE" and "action NW" in names
        assert {f"cell(2,{y})" for y in range(4, 9)} <= set(names)
        assert "cell(4,8)" not in names
        assert res.log_likelihood[-1] > g.mean_log_likelihood(g.solve(true)[0]) + 1.0
        assert false_positive_rate(res.constraint_mask, true) > 0.5


def test_scobee_wall_colours_let_the_greedy_learn_the_wall_as_one_feature():
    """Scobee's own setting: the wall halves are one feature each (his colours) and the
    100 demonstrations are sampled from the maximum-entropy model of the true CMG
    (temperature 1), 20% slip. The green wall's feature gathers the evidence of its
    three cells and is learned right after NE; every reachable true constraint is
    recovered, and the false ones are cells of the dead-end pocket that no
    demonstration happened to enter."""
    solver, cb, reward, demos = scobee_single_expert(RegionIndicatorCostBasis, temperature=1.0)
    true = cb.true_constraints()
    reach = reachable_constraints(solver=solver, reward=reward, cost_basis=cb, true_mask=true)
    assert [cb.names[j] for j in torch.nonzero(reach).flatten()] == [
        "cell(4,5)", "action NE", "action NW", "region green"]
    pocket = {f"cell({x},{y})" for x in (2, 3) for y in range(4, 9)}
    for kind in ("me", "mce"):
        res = GreedyConstraintInference(solver=solver, reward=reward, cost_basis=cb,
                                        demonstrations=demos, model=kind).run()
        names = res.added_names
        assert names[:2] == ["action NE", "region green"]
        assert bool((res.constraint_mask & reach).sum() == reach.sum())
        false = {cb.names[j] for j in torch.nonzero(res.constraint_mask & ~true).flatten()}
        assert false and false <= pocket, names
        assert false_positive_rate(res.constraint_mask, true) <= 0.25


def test_greedy_refuses_bad_input():
    _, model, solver, cb, reward, demos = identifiable_problem(1.0, n_demos=2)
    kw = dict(solver=solver, reward=reward, cost_basis=cb, demonstrations=demos)
    with pytest.raises(ValueError, match="model must be one of"):
        GreedyConstraintInference(model="maxent", **kw)
    with pytest.raises(ValueError, match="epsilon"):
        GreedyConstraintInference(epsilon=-1.0, **kw)
    with pytest.raises(ValueError, match="max_constraints"):
        GreedyConstraintInference(max_constraints=-2, **kw)
    with pytest.raises(TypeError, match="FactoredReward"):
        GreedyConstraintInference(**{**kw, "reward": reward.local})
    f = cb()
    negative = FactoredFeatures(local=f.local - 0.5, joint=f.joint, joint_columns=f.joint_columns)
    with pytest.raises(ValueError, match="non-negative"):
        GreedyConstraintInference(**{**kw, "cost_basis": negative})
    other = TabularGridModel(layout=GridLayout.open_grid(5, 1), horizon=7)
    short = sample_trajectories(FactoredSoftBellman(model=other).solve(
        GoalClosenessRewardBasis(other)().weighted(torch.ones(2, dtype=torch.float64))),
        2, np.random.default_rng(0))
    with pytest.raises(ValueError, match="do not match"):
        GreedyConstraintInference(**{**kw, "demonstrations": short})
    with pytest.raises(ValueError, match="bool mask"):
        constraint_masks(cb(), torch.zeros(3, dtype=torch.bool), model)
    # the default ε is BIC's ln(m) / (2m)
    assert GreedyConstraintInference(**kw).epsilon == pytest.approx(math.log(2) / 4)


def _saved(record: dict) -> dict:
    """``record`` as a checkpoint keeps it: through torch.save / load(weights_only=True)."""
    buffer = io.BytesIO()
    torch.save(record, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


def _outcome(res) -> tuple:
    steps = [dataclasses.replace(s, seconds=0.0) for s in res.steps]
    return (res.constraint_mask.tolist(), res.added, res.added_names, res.log_likelihood,
            res.improvement, steps, res.stop_reason,
            None if res.terminal_value is None else res.terminal_value.tolist())


@pytest.mark.parametrize("problem", ["ME, slip", "MCE, slip", "MCE, infeasible trial"])
def test_greedy_resumed_from_any_saved_step_ends_as_the_uninterrupted_run(problem):
    if problem == "MCE, infeasible trial":  # the records carry an infeasible candidate
        kw, _ = slipped_problem()
        kw["model"] = "mce"
    else:  # ε = 0: on to max_constraints
        _, _, solver, cb, reward, demos = identifiable_problem(0.8, n_demos=30)
        kw = dict(solver=solver, reward=reward, cost_basis=cb, demonstrations=demos,
                  model=problem[:problem.index(",")].lower(), epsilon=0.0, max_constraints=4)
    records: list[dict] = []
    whole = GreedyConstraintInference(**kw).run(on_step=lambda r: records.append(_saved(r)))
    assert len(whole.steps) >= 3, whole.steps
    assert any(s.infeasible for s in whole.steps) == (problem == "MCE, infeasible trial")
    progress = [r["evaluated"] + r["finished"] for r in records]
    assert progress == list(range(1, len(records) + 1))  # one more at every call
    assert records[-1]["finished"] and not any(r["finished"] for r in records[:-1])
    for record in records:
        g = GreedyConstraintInference(**kw)
        resumed = g.run(resume_from=record)
        assert _outcome(resumed) == _outcome(whole), record["evaluated"]
        assert torch.equal(g.expected_accrual(resumed.solution),
                           g.expected_accrual(whole.solution))
        # only the re-solve of the saved set and the trials after it
        assert g.solves == 1 + len(whole.steps) - record["evaluated"]
    # The time counts the search, not the re-solve that resuming costs: a finished
    # record resumed keeps its seconds (up to the bookkeeping after the re-solve).
    t0 = time.perf_counter()
    resumed = GreedyConstraintInference(**kw).run(resume_from=records[-1])
    resume_seconds = time.perf_counter() - t0
    assert 0.0 <= resumed.seconds - records[-1]["seconds"] < 0.5 * resume_seconds


def _two_constraint_greedy_kwargs() -> dict:
    """A 2-constraint MCE greedy on the identifiable problem (20 demonstrations)."""
    _, _, solver, cb, reward, demos = identifiable_problem(1.0, n_demos=20)
    return dict(solver=solver, reward=reward, cost_basis=cb, demonstrations=demos,
                epsilon=0.0, max_constraints=2)


def test_greedy_refuses_progress_of_another_problem_or_setting():
    kw = _two_constraint_greedy_kwargs()
    reward = kw["reward"]
    records: list[dict] = []
    GreedyConstraintInference(**kw).run(on_step=records.append)
    record = records[0]
    with pytest.raises(ValueError, match="was made with .*'epsilon': 0.0"):
        GreedyConstraintInference(**{**kw, "epsilon": 0.1}).run(resume_from=record)
    with pytest.raises(ValueError, match="was made with .*'model': 'mce'"):
        GreedyConstraintInference(**kw, model="me").run(resume_from=record)
    with pytest.raises(ValueError, match="does not belong to this problem"):
        GreedyConstraintInference(**{**kw, "reward": reward.scale(2.0)}
                                  ).run(resume_from=record)
    with pytest.raises(ValueError, match="lacks"):
        GreedyConstraintInference(**kw).run(resume_from={"model": "mce"})
    other = identifiable_problem(1.0, n_demos=1)[-1]
    with pytest.raises(ValueError, match="other candidate constraints"):
        GreedyConstraintInference(**{**kw, "demonstrations": other}).run(resume_from=record)
    g = GreedyConstraintInference(**kw)
    g.resumable = False  # as the SAC greedy, whose model is a warm-started policy
    with pytest.raises(ValueError, match="cannot be resumed"):
        g.run(resume_from=record)


def test_the_runner_runs_a_greedy_that_cannot_resume_again_from_the_start(tmp_path, capsys):
    """A finished run resumed (e.g. to be evaluated again) must not fail at a greedy
    whose model is not in the checkpoint (the drones' SAC greedy): the runner runs it
    from the start, and being seeded it gives the uninterrupted result."""
    from dicrl_torch.runs.checkpoints import Checkpoints
    from dicrl_torch.runs.runner import run_greedy

    kw = _two_constraint_greedy_kwargs()
    path = tmp_path / "checkpoint.pt"
    first = GreedyConstraintInference(**kw)
    first.resumable = False
    done = run_greedy("MCE-greedy", first, Checkpoints(path, False), None)
    again = GreedyConstraintInference(**kw)
    again.resumable = False
    res = run_greedy("MCE-greedy", again, Checkpoints(path, True), None)
    assert "running it again from the start" in capsys.readouterr().out
    assert res.added == done.added and res.log_likelihood == done.log_likelihood
    assert len(res.steps) == len(done.steps)  # every candidate evaluated again


@pytest.mark.parametrize("dtype,close,far", [(torch.float64, 1e-10, 1e-7),
                                             (torch.float32, 3e-7, 1e-3)])
def test_a_record_resumes_through_another_machines_rounding(dtype, close, far):
    """A float32 solve's log-likelihood differs in its last bits on another CPU (vector
    width of the compiled kernels, threads): such a record still resumes; one that differs
    more, as another problem's does, is refused. float64 keeps the tight check."""
    kw = _two_constraint_greedy_kwargs()
    solver = kw["solver"]
    kw["solver"] = FactoredSoftBellman(model=solver.model, dtype=dtype)
    records: list[dict] = []
    whole = GreedyConstraintInference(**kw).run(on_step=records.append)
    record = records[-1]
    saved = record["log_likelihood"][-1]
    nudged = {**record, "log_likelihood": record["log_likelihood"][:-1] + [saved * (1 + close)]}
    assert _outcome(GreedyConstraintInference(**kw).run(resume_from=nudged))[0] == \
        _outcome(whole)[0]
    moved = {**record, "log_likelihood": record["log_likelihood"][:-1] + [saved * (1 + far)]}
    with pytest.raises(ValueError, match="does not belong to this problem"):
        GreedyConstraintInference(**kw).run(resume_from=moved)
