"""Tests of the SAC-style constrained solver (the package dicrl_torch/solvers/sac/).

Kept short (a few thousand env steps in all) and on one CPU thread, so that the numbers
are reproducible and the file runs in well under a minute. What both engines must keep
(relabelling, demonstrations, seeds, clones, best-keeping) runs on both (``ENGINES``);
what is about stable-baselines3's pieces runs on ``engine="sb3"``.
"""

from __future__ import annotations

import copy
import functools
import tempfile
from typing import Any, NamedTuple

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.logger import Logger

from dicrl_torch.demos.drone_demos import make_drone_demonstrations
from dicrl_torch.envs.drones import JointDroneEnv, joint_obs_from_states, joint_obs_to_state
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.solvers.sac import (
    BoxScaler,
    DecomposedSAC,
    FeatureReplayBuffer,
    Lineage,
    SACConstrainedSolver,
    SACSolution,
    discounted_demo_feature_sums,
)

torch.set_num_threads(1)

L_R, L_C = 4, 201
GAMMA = 0.95
ENGINES = ["lean", "sb3"]


def make_solver(seed: int = 0, **kwargs) -> SACConstrainedSolver:
    args = dict(reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(),
                seed=seed, n_envs=2, gamma=GAMMA, learning_starts=100, batch_size=32,
                env_factory=functools.partial(JointDroneEnv, max_steps=30),
                n_eval_episodes=4)
    args.update(kwargs)
    return SACConstrainedSolver(**args)


def random_weights(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    eta = np.concatenate([rng.uniform(0, 2, L_R), [-rng.uniform(0.5, 3)]])
    return eta, rng.uniform(0, 1, L_C)


@functools.cache
def filled_solver(engine: str) -> SACConstrainedSolver:
    """A solver whose buffer holds 200 transitions (2 envs, episodes of 30 steps)."""
    solver = make_solver(seed=1, learning_starts=10_000, engine=engine)  # random actions
    eta, wc = random_weights(np.random.default_rng(0))
    solver.solve(eta, wc, 200, n_eval_episodes=2)
    return solver


@pytest.fixture(scope="module", params=ENGINES)
def filled(request) -> SACConstrainedSolver:
    return filled_solver(request.param)


@pytest.fixture(scope="module")
def filled_sb3() -> SACConstrainedSolver:
    return filled_solver("sb3")


# A stored transition's index: SB3's (batch_inds, env_indices) of FeatureReplayBuffer's
# [buffer_size, n_envs, ...] arrays, or the lean TransitionStore's flat rows.
Index = Any


def hand_rewards(buf: Any, idx: Index, eta: np.ndarray, wc: np.ndarray) -> np.ndarray:
    """``[B]`` float64 rewards of stored transitions ``idx`` from their stored features."""
    phi_r = buf.reward_features[idx].astype(np.float64)
    phi_c = buf.cost_features[idx].astype(np.float64)
    return buf.reward_scale[idx] * (phi_r @ eta[:-1] + eta[-1] * (phi_c @ wc))


def filled_rows(buf: Any) -> Index:
    """Every stored transition's index."""
    if isinstance(buf, FeatureReplayBuffer):
        b, e = np.meshgrid(np.arange(buf.pos), np.arange(buf.n_envs), indexing="ij")
        return b.ravel(), e.ravel()
    return np.arange(buf.size)


def n_rows(idx: Index) -> int:
    return len(idx[0]) if isinstance(idx, tuple) else len(idx)


class Drawn(NamedTuple):
    """A batch ``[B, ...]`` (its last ``demo_rows(B)`` rows demonstrated) and the
    stored index of its other rows."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    dones: torch.Tensor
    index: Index


def draw(buf: Any, n: int, seed: int = 0) -> Drawn:
    """A batch of ``n`` from either engine's replay buffer, on a stream seeded by
    ``seed``. The lean store does not say which rows it drew: they are found back by
    their stored actions (random floats: distinct) and checked by their observations."""
    if isinstance(buf, FeatureReplayBuffer):
        np.random.seed(seed)  # noqa: NPY002 (SB3's sampling stream; deterministic test)
        s = buf.sample(n)
        return Drawn(s.observations, s.actions, s.rewards, s.next_observations, s.dones,
                     buf.last_sample_indices)
    fields, _ = buf.sample(n, torch.Generator().manual_seed(seed))
    k = n - buf.demo_rows(n)
    row_of = {a.numpy().tobytes(): i for i, a in enumerate(buf.actions[:buf.size])}
    assert len(row_of) == buf.size  # every stored action is a row's own
    rows = np.array([row_of[a.numpy().tobytes()] for a in fields[1][:k]], dtype=np.int64)
    assert torch.equal(fields[0][:k], buf.obs[rows])
    assert torch.equal(fields[3][:k], buf.next_obs[rows])
    return Drawn(*fields, rows)


def expected_batch_rewards(buf: Any, idx: Index, eta: np.ndarray,
                           wc: np.ndarray) -> np.ndarray:
    """``[B]`` float32: the rewards a batch must carry for stored transitions ``idx``
    right after ``set_weights(eta, wc)``. SB3 relabels the sampled rows; the lean store
    relabelled every stored row at set_weights, so its float64 arithmetic is that over
    all of them (BLAS may sum a row's dot product in another order for another number
    of rows, which can move the last bit), then cast to float32."""
    if isinstance(buf, FeatureReplayBuffer):
        return hand_rewards(buf, idx, eta, wc).astype(np.float32)
    return hand_rewards(buf, filled_rows(buf), eta, wc)[idx].astype(np.float32)


def assert_stored_rewards(buf: Any, idx: Index, eta: np.ndarray, wc: np.ndarray) -> None:
    """Exactly: the stored transitions ``idx`` carry the rewards of ``(eta, wc)`` from
    their features (SB3: its relabelling of them; lean: the labels it stores for every
    row, and its relabelling of ``idx``)."""
    hand = hand_rewards(buf, idx, eta, wc)
    if isinstance(buf, FeatureReplayBuffer):
        np.testing.assert_array_equal(buf.compute_rewards(*idx), hand)
        return
    everything = hand_rewards(buf, filled_rows(buf), eta, wc)  # as relabelled (above)
    np.testing.assert_array_equal(buf.rewards[:buf.size, 0].numpy(),
                                  everything.astype(np.float32))
    np.testing.assert_array_equal(buf._labels(idx)[:, 0].numpy(), hand.astype(np.float32))


def stored_rewards(buf: Any, idx: Index) -> np.ndarray:
    """``[B]`` the joint rewards stored transitions ``idx`` carry now (SB3: float64
    relabelled; lean: its float32 labels)."""
    if isinstance(buf, FeatureReplayBuffer):
        return buf.compute_rewards(*idx)
    return buf.rewards[idx].numpy().sum(-1)


def actor_params(solver: SACConstrainedSolver) -> list[torch.Tensor]:
    """Copies of the actor's weights (either engine)."""
    return [v.clone() for k, v in solver.policy_state().items() if k.startswith("actor.")]


# ---------------------------------------------------------------------------- buffer
def test_changing_eta_changes_sampled_rewards_of_stored_transitions(filled):
    solver, buf = filled, filled.replay_buffer
    if isinstance(buf, FeatureReplayBuffer):
        assert buf.pos == 100 and buf.n_envs == 2
    else:
        assert buf.size == buf.pos == 200
    rng = np.random.default_rng(5)
    eta1, wc1 = random_weights(rng)
    eta2, wc2 = random_weights(rng)

    solver.set_weights(eta1, wc1)
    s1 = draw(buf, 64, seed=1)
    # Exact: the sampled rewards are the features stored with each transition, weighted
    # by the current weights (float64, then float32 as SB3 stores rewards).
    expect1 = expected_batch_rewards(buf, s1.index, eta1, wc1)
    assert torch.equal(s1.rewards, torch.from_numpy(expect1).reshape(-1, 1))

    solver.set_weights(eta2, wc2)  # new η and ω_c: nothing is re-added to the buffer
    s2 = draw(buf, 64, seed=2)
    expect2 = expected_batch_rewards(buf, s2.index, eta2, wc2)
    assert torch.equal(s2.rewards, torch.from_numpy(expect2).reshape(-1, 1))
    # The very transitions sampled under η1 now carry η2's rewards.
    assert_stored_rewards(buf, s1.index, eta2, wc2)
    assert not np.allclose(stored_rewards(buf, s1.index), hand_rewards(buf, s1.index, eta1,
                                                                       wc1))

    # solve(..., timesteps=0) is the trainer's path: it relabels the buffer as well.
    solver.solve(eta1, wc1, 0, n_eval_episodes=1)
    assert_stored_rewards(buf, s1.index, eta1, wc1)


def test_stored_features_are_those_of_the_next_state(filled):
    buf = filled.replay_buffer
    if isinstance(buf, FeatureReplayBuffer):  # [steps, 2 envs, ...]
        n = buf.pos
        fields = {k: getattr(buf, k)[:n] for k in ("next_states", "reward_features",
                                                   "cost_features", "reward_scale")}
        obs, next_obs = buf.observations[:n], buf.next_observations[:n]
        terminal = buf.dones[:n] * (1 - buf.timeouts[:n])
        assert buf.timeouts[:n].sum() > 0  # time limits are recorded as such
    else:  # flat rows, step by step, env by env: the same [steps, 2 envs, ...] layout
        n = buf.size

        def per_step(x):
            x = x.numpy() if isinstance(x, torch.Tensor) else x
            return x[:n].reshape(n // 2, 2, *x.shape[1:])

        fields = {k: per_step(getattr(buf, k)) for k in ("next_states", "reward_features",
                                                         "cost_features", "reward_scale")}
        obs, next_obs = per_step(buf.obs), per_step(buf.next_obs)
        terminal = per_step(buf.dones)
    states = fields["next_states"]  # [steps, 2 envs, 2, 4]
    obs_states = joint_obs_to_state(next_obs.astype(np.float64))
    np.testing.assert_allclose(states, obs_states, atol=1e-5)  # obs are float32
    phi_c = CellOccupancyCostBasis()(states).numpy()
    np.testing.assert_array_equal(fields["cost_features"], phi_c)  # indicators: exact
    phi_r = DoorLocationRewardBasis()(states).numpy()
    np.testing.assert_allclose(fields["reward_features"], phi_r, rtol=1e-6)
    # Timeouts (max_steps) are truncations, not absorbing terminals: 100 steps per env
    # cut at 30, 60 and 90 (the next observation there is not the next step's).
    assert terminal.sum() == 0
    np.testing.assert_array_equal(fields["reward_scale"], 1.0)
    cut = ~np.all(obs[1:] == next_obs[:-1], axis=-1)  # [steps - 1, 2 envs]
    np.testing.assert_array_equal(cut.sum(0), [3, 3])


def test_terminal_transition_gets_absorbing_value():
    env = JointDroneEnv()
    kw = dict(reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(),
              gamma=0.9)
    buf = FeatureReplayBuffer(10, env.observation_space, env.action_space, "cpu", n_envs=2,
                              state_shape=(2, 4), **kw)
    obs, info = env.reset(seed=0)
    act = np.zeros((2, 4), np.float32)
    infos = [{"state": info["state"]}, {"state": info["state"], "TimeLimit.truncated": True}]
    buf.add(np.stack([obs, obs]), np.stack([obs, obs]), act, np.zeros(2), np.array([1, 1]),
            infos)
    np.testing.assert_allclose(buf.reward_scale[0], [10.0, 1.0])  # 1 / (1 - γ); timeout 1
    buf.set_weights([1.0, 0, 0, 0], -1.0, np.zeros(L_C))
    r = buf.compute_rewards(np.array([0, 0]), np.array([0, 1]))
    np.testing.assert_allclose(r, 10.0 * np.array([1.0, 0.1]) * buf.reward_features[0, :, 0])
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        FeatureReplayBuffer(10, env.observation_space, env.action_space, "cpu",
                            optimize_memory_usage=True, state_shape=(2, 4), **kw)


def test_sampling_before_weights_and_bad_weights_raise():
    buf = FeatureReplayBuffer(8, spaces.Box(-20, 20, (20,)), spaces.Box(-1, 1, (4,)), "cpu",
                              reward_basis=DoorLocationRewardBasis(),
                              cost_basis=CellOccupancyCostBasis(), gamma=0.9,
                              state_shape=(2, 4))
    with pytest.raises(RuntimeError, match="set_weights"):
        buf.compute_rewards(np.array([0]), np.array([0]))
    with pytest.raises(ValueError, match=r"reward_weights must have shape \[4\]"):
        buf.set_weights(np.ones(5), -1.0, np.ones(L_C))
    with pytest.raises(ValueError, match="multiplier"):
        buf.set_weights(np.ones(4), float("nan"), np.ones(L_C))


# ---------------------------------------------------------------------------- solver
@pytest.mark.parametrize("engine", ENGINES)
def test_ent_coef_fixed_and_warm_start_keeps_networks_and_buffer(engine):
    solver = make_solver(seed=2, ent_coef=0.7, engine=engine)

    def held():  # what must survive a solve: the networks and the replay buffer
        if engine == "sb3":
            m = solver.engine.model
            return (m, m.actor, m.critic, m.replay_buffer)
        sac = solver.engine.sac
        return (sac, sac.actor, sac.critic, solver.replay_buffer)

    def stored():
        return buf.pos if engine == "sb3" else buf.size  # SB3: rows of 2 envs

    before, buf = held(), solver.replay_buffer
    eta, wc = random_weights(np.random.default_rng(1))
    solver.solve(eta, wc, 200, n_eval_episodes=1)
    params1 = actor_params(solver)
    assert solver.num_timesteps == 200 and stored() == (100 if engine == "sb3" else 200)
    assert solver.n_updates > 0

    eta2, wc2 = random_weights(np.random.default_rng(2))
    solver.solve(eta2, wc2, 100, n_eval_episodes=1)
    assert all(x is y for x, y in zip(held(), before, strict=True))
    assert solver.replay_buffer is buf  # appended, not reset
    assert stored() == (150 if engine == "sb3" else 300)
    assert solver.num_timesteps == 300  # counting went on
    assert any(not torch.equal(a, p) for a, p in zip(params1, actor_params(solver),
                                                     strict=True))
    # The temperature never moved.
    if engine == "sb3":  # no optimiser, the tensor still 0.7
        model = solver.engine.model
        assert model.ent_coef_optimizer is None and model.log_ent_coef is None
        assert float(model.ent_coef_tensor) == pytest.approx(0.7)
    else:  # a plain float of the update, never a parameter
        assert solver.engine.sac.alpha == 0.7
    np.testing.assert_array_equal(buf.cost_weights, wc2)


@pytest.mark.parametrize("engine", ENGINES)
def test_solving_leaves_no_directories_in_the_temp_dir(tmp_path, monkeypatch, engine):
    # SB3's default logger makes an SB3-<time> directory per learn() call.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    solver = make_solver(seed=6, engine=engine)
    eta, wc = random_weights(np.random.default_rng(6))
    solver.solve(eta, wc, 60, n_eval_episodes=1)
    solver.solve(eta, wc, 60, n_eval_episodes=1)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("bad", ["auto", "auto_0.1", 0.0, -1.0, float("nan")])
def test_ent_coef_must_be_fixed_positive(bad):
    with pytest.raises(ValueError, match="ent_coef"):
        make_solver(ent_coef=bad)


def test_bad_arguments_raise_value_errors():
    with pytest.raises(ValueError, match="seed"):
        make_solver(seed=None)
    with pytest.raises(ValueError, match="sac_kwargs must not set 'ent_coef'"):
        make_solver(sac_kwargs={"ent_coef": "auto"}, engine="sb3")
    with pytest.raises(ValueError, match=r"sac_kwargs \['ent_coef', 'tau'\] are "
                                         r"stable-baselines3 options; they need engine='sb3'"):
        make_solver(sac_kwargs={"tau": 0.01, "ent_coef": "auto"})  # engine="lean", default
    with pytest.raises(ValueError, match="engine must be one of"):
        make_solver(engine="SB3")
    solver = make_solver()
    with pytest.raises(ValueError, match=r"eta must have shape \[5\]"):
        solver.solve(np.ones(4), np.ones(L_C), 0)
    with pytest.raises(ValueError, match=r"cost_weights must have shape \[201\]"):
        solver.solve(np.ones(5), np.ones(3), 0)
    with pytest.raises(ValueError, match="timesteps"):
        solver.solve(np.ones(5), np.ones(L_C), -1)


def test_feature_expectations_shapes_and_range():
    solver = make_solver(seed=3)
    eta, wc = random_weights(np.random.default_rng(3))
    sol = solver.solve(eta, wc, 0, n_eval_episodes=6)
    assert sol.mu_r.shape == (L_R,) and sol.mu_c.shape == (L_C,)
    assert sol.mu_r_se.shape == (L_R,) and sol.mu_c_se.shape == (L_C,)
    assert sol.reward_sums.shape == (6, L_R) and sol.cost_sums.shape == (6, L_C)
    assert torch.equal(sol.feature_expectation(solver.reward_basis), sol.mu_r)
    assert torch.equal(sol.feature_expectation("cost"), sol.mu_c)
    with pytest.raises(ValueError, match="reward_basis or cost_basis"):
        sol.feature_expectation(DoorLocationRewardBasis())
    # Features lie in [0, max_value], so discounted sums lie in [0, max / (1 - γ)].
    for sums, basis in ((sol.reward_sums, solver.reward_basis),
                        (sol.cost_sums, solver.cost_basis)):
        assert sums.min() >= 0 and sums.max() <= basis.max_value / (1 - GAMMA) + 1e-9
    # One-hot cells: each drone's block sums to the episode's discount mass (30 steps,
    # timeouts: no absorbing bonus).
    assert torch.equal(sol.lengths, torch.full((6,), 30))
    mass = (1 - GAMMA**30) / (1 - GAMMA)
    blocks = sol.cost_sums[:, :200].reshape(6, 2, 100).sum(-1)
    torch.testing.assert_close(blocks, torch.full((6, 2), mass, dtype=torch.float64))
    j, se = sol.cost_value()
    assert j == pytest.approx(float(sol.mu_c @ torch.from_numpy(wc)))
    assert se > 0 and torch.all(sol.mu_r_se > 0)
    assert 0.0 <= sol.success_rate <= 1.0 and 0.0 <= sol.violation_rate <= 1.0


@pytest.mark.parametrize("engine", ENGINES)
def test_same_seed_same_numbers_and_caller_rng_untouched(engine):
    eta, wc = random_weights(np.random.default_rng(4))
    torch_state, np_state = torch.get_rng_state(), np.random.get_state()  # noqa: NPY002
    runs = []
    for seed in (7, 7, 8):
        solver = make_solver(seed=seed, engine=engine)
        sol = solver.solve(eta, wc, 150)
        assert solver.n_updates > 0
        runs.append((sol, solver.policy_state()))  # actor, critics and target critics
    (a, pa), (b, pb), (c, pc) = runs
    assert torch.equal(a.reward_sums, b.reward_sums) and torch.equal(a.cost_sums, b.cost_sums)
    assert pa.keys() == pb.keys() == pc.keys()
    assert all(torch.equal(pa[k], pb[k]) for k in pa)
    assert not torch.equal(a.reward_sums, c.reward_sums)
    assert not all(torch.equal(pa[k], pc[k]) for k in pa)
    # The solver ran on its own streams: the caller's global generators did not move.
    assert torch.equal(torch.get_rng_state(), torch_state)
    after = np.random.get_state()  # noqa: NPY002
    assert np.array_equal(after[1], np_state[1]) and after[2] == np_state[2]


def test_short_training_increases_a_trivial_reward():
    # Reward: progress of both drones towards their doors. At temperature 0.1 relative
    # to weights 5 (i.e. ent_coef 1 at weights 50) SAC learns it in ~1.5k steps.
    solver = make_solver(seed=0, n_envs=1, ent_coef=0.1, learning_rate=1e-3, batch_size=64,
                         learning_starts=200,
                         env_factory=functools.partial(JointDroneEnv, max_steps=40),
                         n_eval_episodes=16)
    eta = np.array([5.0, 0.0, 5.0, 0.0, 0.0])
    w = torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    before = solver.solve(eta, np.zeros(L_C), 0)
    after = solver.solve(eta, np.zeros(L_C), 1500)
    gain = float((after.mu_r - before.mu_r) @ w)
    var = (before.reward_sums @ w).var() + (after.reward_sums @ w).var()
    se = float((var / 16).sqrt())  # standard error of the difference of the means
    assert gain > 2 * se and gain > 0.2, (gain, se)


# ---------------------------------------------------------------- demonstrations
@pytest.fixture(scope="module")
def demos():
    return make_drone_demonstrations(2, rng=np.random.default_rng(0))


@pytest.mark.parametrize("engine", ENGINES)
def test_log_likelihood_matches_sb3_density(demos, engine):
    solver = make_solver(seed=5, engine=engine)
    per = solver.log_likelihood(demos, per_episode=True)
    assert per.shape == (2,) and torch.isfinite(per).all()
    assert solver.log_likelihood(demos) == pytest.approx(float(per.sum()))
    # Cross-check the first step (both drones fly) against SB3's own squashed density.
    obs = torch.from_numpy(joint_obs_from_states(demos.states[:, 0]))
    act = torch.tensor(demos.actions[:, 0].reshape(2, 4), dtype=torch.float32)
    with torch.no_grad():
        if engine == "sb3":
            actor = solver.engine.model.actor
            mean, log_std, _ = actor.get_action_dist_params(obs)
            dist = actor.action_dist
        else:  # the lean actor's own parameters, SB3's density of them
            scaled = torch.from_numpy(solver.engine.scale(obs.numpy()))
            mean, log_std = (x[0] for x in solver.engine.sac.actor.dist_params(scaled[None]))
            dist = SquashedDiagGaussianDistribution(4)
        sb3 = dist.proba_distribution(mean, log_std).log_prob(act)
    # Demonstrations cut to their first step isolate that step's log-density.
    one = type(demos)(states=demos.states[:, :2], actions=demos.actions[:, :1],
                      lengths=np.ones(2, np.int64), dt=demos.dt)
    torch.testing.assert_close(solver.log_likelihood(one, per_episode=True), sb3.double(),
                               rtol=1e-4, atol=1e-4)


def test_joint_obs_round_trip_and_demo_feature_sums(demos):
    env = JointDroneEnv()
    obs, info = env.reset(seed=3)
    np.testing.assert_array_equal(joint_obs_from_states(info["state"]), obs)
    basis = DoorLocationRewardBasis()
    sums = discounted_demo_feature_sums(demos, basis, 0.9)
    assert sums.shape == (2, L_R)
    k, L = 0, int(demos.lengths[0])
    phi = basis(demos.states[k, 1:L + 1]).double()  # [L, l]
    w = 0.9 ** torch.arange(L, dtype=torch.float64)
    w[-1] /= 0.1
    torch.testing.assert_close(sums[k], w @ phi)
    plain = discounted_demo_feature_sums(demos, basis, 0.9, absorbing=False)
    torch.testing.assert_close(plain[k], (0.9 ** torch.arange(L, dtype=torch.float64)) @ phi)


def demo_transition_table(demos, solver: SACConstrainedSolver, eta: np.ndarray,
                          wc: np.ndarray) -> dict[bytes, tuple[float, float, np.ndarray]]:
    """Every demonstrated transition, computed straight from the pairs and the bases:
    ``(o_t, o_{t+1})`` bytes -> (reward under ``eta, wc``, done, action)."""
    table = {}
    for k in range(demos.n_pairs):
        L = int(demos.lengths[k])
        for t in range(L):
            s1 = torch.from_numpy(np.array(demos.states[k, t + 1]))
            r = (float(solver.reward_basis(s1) @ torch.from_numpy(eta[:-1]))
                 + eta[-1] * float(solver.cost_basis(s1) @ torch.from_numpy(wc)))
            last = t == L - 1
            key = (joint_obs_from_states(demos.states[k, t]).tobytes()
                   + joint_obs_from_states(demos.states[k, t + 1]).tobytes())
            table[key] = ((1 / (1 - GAMMA) if last else 1.0) * r, float(last),
                          np.array(demos.actions[k, t]).reshape(-1))
    return table


@pytest.mark.parametrize("engine", ENGINES)
def test_demonstrated_transitions_fill_their_share_of_each_batch(demos, engine):
    """With demo_fraction 0.25, the last quarter of each batch are the learner's own
    demonstrated transitions, relabelled under the current weights (the last one of a
    pair terminal and absorbing); the rest come from the env as before."""
    solver = make_solver(seed=3, learning_starts=10_000, demo_fraction=0.25, engine=engine)
    rng = np.random.default_rng(4)
    solver.solve(*random_weights(rng), 200, n_eval_episodes=1)
    solver.set_demonstrations(demos)
    buf = solver.replay_buffer
    stored_obs = buf.observations if engine == "sb3" else buf.obs.numpy()
    for seed in range(2):  # new weights relabel the demonstrated transitions too
        eta, wc = random_weights(rng)
        solver.set_weights(eta, wc)
        table = demo_transition_table(demos, solver, eta, wc)
        batch = draw(buf, 400, seed=seed)
        assert batch.obs.shape == (400, 20) and batch.rewards.shape == (400, 1)
        assert n_rows(batch.index) == 300
        np.testing.assert_array_equal(batch.obs[:300].numpy(), stored_obs[batch.index])
        np.testing.assert_allclose(batch.rewards[:300, 0].numpy(),
                                   hand_rewards(buf, batch.index, eta, wc), rtol=1e-5,
                                   atol=1e-4)
        done = []
        for i in range(300, 400):
            key = batch.obs[i].numpy().tobytes() + batch.next_obs[i].numpy().tobytes()
            reward, d, action = table[key]
            assert float(batch.rewards[i, 0]) == pytest.approx(reward, rel=1e-5, abs=1e-4)
            np.testing.assert_allclose(batch.actions[i].numpy(), action, atol=1e-6)
            done.append(float(batch.dones[i, 0]) == d)
        assert all(done)
        assert any(d for _, d, _ in table.values())  # the pairs' last steps are terminal
    solver.set_demonstrations(None)
    batch = draw(buf, 40)
    assert len(batch.obs) == 40 and n_rows(batch.index) == 40


def test_demonstrations_are_refused_when_malformed(demos):
    with pytest.raises(ValueError, match="demo_fraction"):
        make_solver(demo_fraction=1.0)
    solver = make_solver(demo_fraction=0.5)
    with pytest.raises(ValueError, match="ContinuousDemonstrations"):
        solver.set_demonstrations(np.zeros((2, 10, 2, 4)))
    with pytest.raises(ValueError, match="fraction"):
        solver.replay_buffer.set_demonstrations(demos, -0.1)


def test_box_scaler_maps_the_bounds_onto_unit_box():
    """BoxScaler sends each bounded coordinate's low/high to -1/+1 (constant ones to 0),
    and scale_observations=True puts it in front of the actor and both critics."""
    space = spaces.Box(low=np.array([0.0, -1.5, 5.0], dtype=np.float32),
                       high=np.array([10.0, 1.5, 5.0], dtype=np.float32))
    scaler = BoxScaler(space)
    obs = torch.tensor([[0.0, -1.5, 5.0], [10.0, 1.5, 5.0], [2.5, 0.75, 5.0]])
    expected = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-0.5, 0.5, 0.0]])
    torch.testing.assert_close(scaler(obs), expected)
    with pytest.raises(ValueError, match="finite"):
        BoxScaler(spaces.Box(low=-np.inf, high=np.inf, shape=(2,), dtype=np.float32))
    solver = make_solver(scale_observations=True, engine="sb3")
    policy = solver.engine.model.policy
    for extractor in (policy.actor.features_extractor, policy.critic.features_extractor,
                      policy.critic_target.features_extractor):
        assert isinstance(extractor, BoxScaler)
    env_space = solver.engine.vec_env.observation_space
    low = torch.as_tensor(env_space.low)[None]
    torch.testing.assert_close(policy.actor.features_extractor(low),
                               -torch.ones_like(low))  # every bound spans an interval
    # The lean engine scales the same way, before storing and acting.
    lean = make_solver(scale_observations=True).engine
    high = torch.as_tensor(env_space.high)[None]
    for bound in (low, high, torch.from_numpy(solver._env.observation_space.sample()[None])):
        torch.testing.assert_close(torch.from_numpy(lean.scale(bound.numpy())),
                                   policy.actor.features_extractor(bound))
    with pytest.raises(ValueError, match="scale_observations must be a bool"):
        make_solver(scale_observations="yes")
    with pytest.raises(ValueError, match="drop features_extractor_class"):
        make_solver(scale_observations=True, engine="sb3",
                    sac_kwargs={"policy_kwargs": {"features_extractor_class": BoxScaler}})


# ------------------------------------------------------------------ per-agent critics
def hand_drone_rewards(buf: Any, idx: Index, eta: np.ndarray, wc: np.ndarray) -> np.ndarray:
    """``[B, 2]`` each drone's reward from the bases' layout: its 2 reward features, its
    100 cells and half the proximity (the last cost feature)."""
    phi_r = buf.reward_features[idx].astype(np.float64)
    phi_c = buf.cost_features[idx].astype(np.float64)
    cols = []
    for g in range(2):
        own_r = slice(2 * g, 2 * g + 2)
        own_c = slice(100 * g, 100 * g + 100)
        cols.append(phi_r[:, own_r] @ eta[own_r] + eta[-1] * (
            phi_c[:, own_c] @ wc[own_c] + 0.5 * phi_c[:, 200] * wc[200]))
    return buf.reward_scale[idx][:, None] * np.stack(cols, 1)


@pytest.mark.parametrize("engine", ENGINES)
def test_per_agent_rewards_are_each_drones_share_of_the_joint_reward(engine):
    solver = make_solver(seed=3, learning_starts=10_000, per_agent_critics=True,
                         engine=engine)
    rng = np.random.default_rng(8)
    eta, wc = random_weights(rng)
    wc[200] = 2.0  # make the shared proximity's split visible
    solver.solve(eta, wc, 200, n_eval_episodes=1)
    buf = solver.replay_buffer
    batch = draw(buf, 64)
    idx = batch.index
    assert batch.rewards.shape == (64, 2)
    expected = hand_drone_rewards(buf, idx, eta, wc)
    np.testing.assert_allclose(batch.rewards.numpy(), expected, rtol=1e-6, atol=1e-6)
    # The columns add up to the joint reward the plain buffer samples.
    if engine == "sb3":
        joint = buf.compute_rewards(*idx)
    else:  # the float64 columns the lean store casts to its float32 labels
        joint = buf._relabel(buf.reward_features[idx], buf.cost_features[idx],
                             buf.reward_scale[idx]).sum(-1)
    np.testing.assert_allclose(joint, hand_rewards(buf, idx, eta, wc), rtol=1e-12)
    assert not np.allclose(expected[:, 0], expected[:, 1])


def test_decomposed_sac_with_one_reward_column_matches_sb3_sac(filled_sb3):
    """DecomposedSAC.train is our own loop: with one reward column it must make SB3's
    SAC updates (same batch, same random numbers)."""
    sb3 = copy.deepcopy(filled_sb3.engine.model)
    mine = DecomposedSAC("MlpPolicy", filled_sb3.engine.vec_env, learning_rate=3e-4,
                         gamma=GAMMA, tau=0.005, batch_size=32, ent_coef=1.0, device="cpu",
                         policy_kwargs={"net_arch": [64, 64], "n_rewards": 1})
    mine.set_logger(Logger(folder=None, output_formats=[]))
    mine.policy.load_state_dict(sb3.policy.state_dict())
    mine.actor.optimizer.load_state_dict(sb3.actor.optimizer.state_dict())
    mine.critic.optimizer.load_state_dict(sb3.critic.optimizer.state_dict())
    mine.replay_buffer = copy.deepcopy(sb3.replay_buffer)
    before = {k: v.clone() for k, v in sb3.policy.state_dict().items()}
    np_state = np.random.get_state()  # noqa: NPY002 (SB3 samples from the global stream)
    with torch.random.fork_rng():
        for model in (sb3, mine):
            torch.manual_seed(0)
            np.random.seed(0)  # noqa: NPY002
            model.train(gradient_steps=5, batch_size=32)
    np.random.set_state(np_state)  # noqa: NPY002
    ours, theirs = mine.policy.state_dict(), sb3.policy.state_dict()
    assert ours.keys() == theirs.keys()
    for key in theirs:
        torch.testing.assert_close(ours[key], theirs[key], rtol=1e-5, atol=1e-6, msg=key)
    assert not torch.equal(theirs["critic.qf0.0.weight"], before["critic.qf0.0.weight"])
    assert not torch.equal(theirs["actor.mu.weight"], before["actor.mu.weight"])


@pytest.mark.parametrize("engine", ENGINES)
def test_per_agent_critics_train_one_column_per_drone(engine):
    solver = make_solver(per_agent_critics=True, engine=engine)
    eta, wc = random_weights(np.random.default_rng(2))
    solver.solve(eta, wc, 300, n_eval_episodes=1)
    assert solver.n_updates > 0
    batch = draw(solver.replay_buffer, 16)
    if engine == "sb3":
        qs = solver.engine.model.critic(batch.obs, batch.actions)
    else:  # [1 learner, 2 critics, B, G]
        critic = solver.engine.sac.critic
        qs = critic.forward_with(critic.params, batch.obs[None], batch.actions[None])[0]
    assert len(qs) == 2
    for q in qs:
        assert q.shape == (16, 2) and torch.isfinite(q).all()
    with pytest.raises(ValueError, match="per_agent_critics must be a bool"):
        make_solver(per_agent_critics=1, engine=engine)

    class Anonymous(torch.nn.Module):  # a basis that cannot say whose features are whose
        dim = 4

        def forward(self, states, actions=None):
            return torch.zeros(*np.shape(states)[:-2], 4, dtype=torch.float64)

    with pytest.raises(ValueError, match="agent_shares"):
        make_solver(per_agent_critics=True, reward_basis=Anonymous(), engine=engine)
    if engine == "sb3":
        with pytest.raises(ValueError, match="fixed ent_coef"):
            DecomposedSAC("MlpPolicy", solver.engine.vec_env, ent_coef="auto",
                          policy_kwargs={"n_rewards": 2})


# ------------------------------------------------------------ keeping the best iterate
def assert_same_networks(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    """Two :meth:`SACConstrainedSolver.policy_state` values are equal, tensor by tensor."""
    assert a.keys() == b.keys()
    for key, value in a.items():
        assert torch.equal(value, b[key]), key


# Seeds whose runs show what the tests below need (the engines draw differently).
BEST_NOT_LAST = {"lean": 7, "sb3": 6}  # the best of 3 chunks is not the last
CLONE_WINS = {"lean": 5, "sb3": 8}  # of 2 lineages, the clone's first chunk is the best
THIRD_WINS = {"lean": 1, "sb3": 12}  # of 3 lineages, a chunk of the third is the best


@pytest.mark.parametrize("engine", ENGINES)
def test_solve_keeping_best_ends_on_the_best_scored_chunk(engine):
    eta, wc = random_weights(np.random.default_rng(4))
    seed = BEST_NOT_LAST[engine]
    kept = make_solver(seed=seed, learning_starts=50, engine=engine)
    best = kept.solve_keeping_best(eta, wc, 300, checks=3, n_eval_episodes=3,
                                   deterministic=True)
    # The same seed stepped by hand: chunk by chunk, with the same rollouts.
    manual = make_solver(seed=seed, learning_starts=50, engine=engine)
    scores, states = [], []
    for steps in (100, 100, 100):
        manual._train(eta, wc, steps)
        sol = manual.evaluate(3, deterministic=True)
        per = (sol.reward_sums.numpy() @ eta[:-1]
               + eta[-1] * (sol.cost_sums.numpy() @ wc))
        scores.append(float(per.mean()))
        states.append(manual.policy_state())
    assert best.penalised_return()[0] == pytest.approx(max(scores), rel=1e-12)
    assert [c["timesteps"] for c in kept.last_checks] == [100, 200, 300]
    np.testing.assert_allclose([c["penalised_return"] for c in kept.last_checks], scores,
                               rtol=1e-12)
    assert all(c["success_under_constraints"] is None for c in kept.last_checks)
    assert len(set(scores)) == 3  # the chunks' policies differ
    assert int(np.argmax(scores)) < 2  # (this seed) the best is not the last: restored
    assert_same_networks(kept.policy_state(), states[int(np.argmax(scores))])
    # One check is solve(): the same networks.
    once, plain = (make_solver(seed=seed, engine=engine) for _ in range(2))
    once.solve_keeping_best(eta, wc, 150, checks=1, n_eval_episodes=1)
    plain.solve(eta, wc, 150, n_eval_episodes=1)
    assert plain.n_updates > 0
    assert_same_networks(once.policy_state(), plain.policy_state())
    with pytest.raises(ValueError, match="checks must be a positive int"):
        kept.solve_keeping_best(eta, wc, 10, checks=0)
    with pytest.raises(ValueError, match="timesteps must be an int >= checks=4"):
        kept.solve_keeping_best(eta, wc, 3, checks=4)


@pytest.mark.parametrize("engine", ENGINES)
def test_solve_keeping_best_restarts_are_clones_scored_like_the_solver(engine):
    """restarts=2: the solver's own lineage, then a clone made before any chunk (seeded
    from the solver's seed), stepped by hand; the best chunk of either is kept."""
    eta, wc = random_weights(np.random.default_rng(5))
    seed = CLONE_WINS[engine]
    kept, manual = (make_solver(seed=seed, learning_starts=50, engine=engine)
                    for _ in range(2))
    for solver in (kept, manual):
        solver._train(eta, wc, 100)  # a state worth restarting from
    best = kept.solve_keeping_best(eta, wc, 100, checks=2, restarts=2, n_eval_episodes=3,
                                   deterministic=True)
    twin = manual.clone(int(np.random.SeedSequence([seed, 4]).generate_state(1)[0]))
    scores, states = [], []
    for solver in (manual, twin):
        for _ in range(2):
            solver._train(eta, wc, 50)
            sol = solver.evaluate(3, deterministic=True)
            scores.append(sol.penalised_return()[0])
            states.append(solver.policy_state())
    assert [(c["restart"], c["timesteps"]) for c in kept.last_checks] == [
        (0, 150), (0, 200), (1, 150), (1, 200)]
    np.testing.assert_allclose([c["penalised_return"] for c in kept.last_checks], scores,
                               rtol=1e-12)
    assert scores[2:] != scores[:2]  # the clone's lineage is its own
    assert best.penalised_return()[0] == pytest.approx(max(scores), rel=1e-12)
    assert best.solver is kept
    assert int(np.argmax(scores)) == 2  # (this seed) the clone's: its networks adopted
    assert_same_networks(kept.policy_state(), states[int(np.argmax(scores))])
    with pytest.raises(ValueError, match="restarts must be a positive int"):
        kept.solve_keeping_best(eta, wc, 10, checks=1, restarts=0)


def test_a_lineage_stops_at_its_first_chunk_reaching_stop_at(monkeypatch):
    """stop_at: a lineage ends after the first chunk whose success reaches it; the steps
    left are not trained and that chunk's networks are kept. The scores are made up (the
    share of drones at their doors: 0.5, then 1.0), the training real: the networks are
    those of 200 steps trained by hand."""
    from dataclasses import replace

    eta, wc = random_weights(np.random.default_rng(4))
    none = torch.zeros(L_C, dtype=torch.bool)
    shares = iter([0.5, 1.0, 1.0])

    def scored(solver):
        evaluate = solver.evaluate

        def with_share(*args, **kwargs):
            sol = evaluate(*args, **kwargs)
            reached = torch.zeros_like(sol.reached)
            reached.view(-1)[:int(round(next(shares) * reached.numel()))] = True
            return replace(sol, reached=reached)
        monkeypatch.setattr(solver, "evaluate", with_share)
        return solver

    kept = scored(make_solver(seed=3, learning_starts=50))
    best = kept.solve_keeping_best(eta, wc, 300, checks=3, n_eval_episodes=2,
                                   deterministic=True, constraints=none, stop_at=1.0)
    assert [c["timesteps"] for c in kept.last_checks] == [100, 200]
    assert [c["success_under_constraints"] for c in kept.last_checks] == [0.5, 1.0]
    assert kept.num_timesteps == 200 and best.success_rate_under(none) == 1.0
    manual = make_solver(seed=3, learning_starts=50)
    for _ in range(2):
        manual._train(eta, wc, 100)
        manual.evaluate(2, deterministic=True)  # the same rollouts drawn
    assert_same_networks(kept.policy_state(), manual.policy_state())
    for bad, constraints in ((0.0, none), (1.5, none), (True, none), (1.0, None)):
        with pytest.raises(ValueError, match="stop_at must be a success rate"):
            kept.solve_keeping_best(eta, wc, 10, checks=2, constraints=constraints,
                                    stop_at=bad)


def test_success_under_constraints_counts_each_drones_own_features():
    """success_rate_under against a hand count over a solution with made-up rollouts."""
    solver = make_solver()
    n, l_c = 4, L_C
    cost = torch.zeros(n, l_c, dtype=torch.float64)
    cost[0, 45] = 0.3          # drone 0 entered its cell (5,4)
    cost[1, 100 + 45] = 0.2    # drone 1 entered its cell (5,4)
    cost[2, 200] = 0.1         # the drones came too close
    reached = torch.tensor([[True, True], [True, False], [True, True], [True, True]])
    sol = SACSolution(reward_sums=torch.zeros(n, L_R), cost_sums=cost,
                      lengths=torch.full((n,), 10), reached=reached,
                      violated=torch.zeros(n, 2, dtype=torch.bool), eta=None,
                      cost_weights=None, timesteps=0, solver=solver)
    mask = np.zeros(l_c, dtype=bool)
    assert sol.success_rate_under(mask) == 7 / 8  # only the drone that did not arrive
    mask[45] = True  # drone 0's (5,4): episode 0 loses drone 0
    assert sol.success_rate_under(mask) == 6 / 8
    mask[145] = True  # drone 1's (5,4): drone 1 of episode 1 had not arrived anyway
    assert sol.success_rate_under(mask) == 6 / 8
    mask[200] = True  # the proximity: both drones of episode 2
    assert sol.success_rate_under(mask) == 4 / 8
    with pytest.raises(ValueError, match="constraints must be"):
        sol.success_rate_under(np.zeros(5, dtype=bool))


# ------------------------------------------------------------ penalty with a margin
def test_grown_cells_fire_within_the_margin_of_each_cell():
    """CellOccupancyCostBasis.dilated(δ): a drone counts in cell (ix, iy) exactly when it
    lies in the cell's square grown by δ on every side (brute force over the 100 cells),
    the proximity fires below radius + δ, and δ = 0 is the plain one-hot."""
    rng = np.random.default_rng(0)
    states = np.zeros((500, 2, 4))
    states[..., :2] = rng.uniform(0, 9.9, (500, 2, 2))  # inside the room
    states[:100, :, :2] = np.round(states[:100, :, :2], 1)  # on and near cell edges
    plain, margin = CellOccupancyCostBasis(), 0.25  # no position lies δ from an edge
    grown = plain.dilated(margin)
    phi, phi_grown = plain(states).numpy(), grown(states).numpy()
    for i in range(2):
        x, y = states[:, i, 0, None], states[:, i, 1, None]
        cells = np.arange(100)
        ix, iy = cells % 10, cells // 10
        inside = (x >= ix) & (x < ix + 1) & (y >= iy) & (y < iy + 1)
        near = ((x >= ix - margin) & (x < ix + 1 + margin)
                & (y >= iy - margin) & (y < iy + 1 + margin))
        np.testing.assert_array_equal(phi[:, 100 * i:100 * (i + 1)], inside)
        np.testing.assert_array_equal(phi_grown[:, 100 * i:100 * (i + 1)], near)
    gap = np.linalg.norm(states[:, 0, :2] - states[:, 1, :2], axis=-1)
    np.testing.assert_array_equal(phi_grown[:, -1], gap < plain.proximity_radius + margin)
    assert (phi_grown.sum(-1) > phi.sum(-1)).any()
    np.testing.assert_array_equal(CellOccupancyCostBasis(margin=0.0)(states), phi)
    for bad in (-0.1, 0.5, float("nan")):
        with pytest.raises(ValueError, match="margin must lie in"):
            plain.dilated(bad)


@pytest.mark.parametrize("engine", ENGINES)
def test_a_penalty_basis_relabels_stored_and_demonstrated_transitions(demos, engine):
    """With a penalty basis set, the cost part of every sampled reward is λ ω_c · φ of
    that basis at the transition's next state (env rows and demonstrated rows alike);
    set back to None, the stored features again."""
    solver = make_solver(seed=3, learning_starts=10_000, demo_fraction=0.25, engine=engine)
    rng = np.random.default_rng(4)
    solver.solve(*random_weights(rng), 200, n_eval_episodes=1)
    solver.set_demonstrations(demos)
    buf, grown = solver.replay_buffer, CellOccupancyCostBasis().dilated(0.3)
    eta, wc = random_weights(rng)
    solver.set_weights(eta, wc)
    buf.set_penalty_basis(grown)
    batch = draw(buf, 400, seed=1)
    idx = batch.index
    phi_r = buf.reward_features[idx].astype(np.float64)
    phi_grown = grown(buf.next_states[idx]).numpy()
    expect = buf.reward_scale[idx] * (phi_r @ eta[:-1] + eta[-1] * (phi_grown @ wc))
    np.testing.assert_allclose(batch.rewards[:300, 0].numpy(), expect, rtol=1e-5, atol=1e-4)
    assert not np.allclose(expect, hand_rewards(buf, idx, eta, wc))  # the margin counts
    grown_solver = copy.copy(solver)
    grown_solver.cost_basis = grown  # the demonstrated rows' rewards, from the pairs
    table = demo_transition_table(demos, grown_solver, eta, wc)
    for i in range(300, 400):
        key = batch.obs[i].numpy().tobytes() + batch.next_obs[i].numpy().tobytes()
        assert float(batch.rewards[i, 0]) == pytest.approx(table[key][0], rel=1e-5, abs=1e-4)
    buf.set_penalty_basis(None)
    again = draw(buf, 64, seed=2)
    assert_stored_rewards(buf, again.index, eta, wc)
    with pytest.raises(ValueError, match="penalty_basis has 4 features"):
        buf.set_penalty_basis(DoorLocationRewardBasis())


@pytest.mark.parametrize("engine", ENGINES)
def test_solve_keeping_best_trains_on_the_penalty_basis_for_that_solve_only(engine):
    """The last solve with a penalty basis: the chunks train on it (another policy than
    without), the scores keep the cost basis, and the buffer is back on φ_c after."""
    eta, wc = random_weights(np.random.default_rng(4))
    grown = CellOccupancyCostBasis().dilated(0.4)
    with_margin, plain = (make_solver(seed=6, learning_starts=50, engine=engine)
                          for _ in range(2))
    seen = []
    original = with_margin.replay_buffer._penalty_features

    def spy(*args):
        seen.append(with_margin.replay_buffer.penalty_basis)
        return original(*args)

    with_margin.replay_buffer._penalty_features = spy
    a = with_margin.solve_keeping_best(eta, wc, 200, checks=2, n_eval_episodes=2,
                                       penalty_basis=grown)
    b = plain.solve_keeping_best(eta, wc, 200, checks=2, n_eval_episodes=2)
    if engine == "sb3":  # relabelled at every sample, all of them during the solve
        assert seen and all(basis is grown for basis in seen)
    else:  # labelled at set_weights and add, during the solve; then relabelled on φ_c
        assert len(seen) > 2 and all(basis is grown for basis in seen[:-1])
        assert seen[-1] is None
    assert with_margin.replay_buffer.penalty_basis is None
    buf = with_margin.replay_buffer
    assert_stored_rewards(buf, filled_rows(buf), eta, wc)  # φ_c's rewards again
    assert a.cost_sums.shape == b.cost_sums.shape  # estimates in the cost basis
    mine, theirs = with_margin.policy_state(), plain.policy_state()
    assert mine.keys() == theirs.keys()
    assert any(not torch.equal(mine[k], theirs[k]) for k in mine)


def test_buffer_state_without_demonstrated_states_loads_and_refuses_a_margin(demos):
    """A state saved before the demonstrations' next states were kept (SB3's buffer: the
    lean store's states always hold them) still loads; a penalty basis then asks for
    the demonstrations again (naming the fix)."""
    solver = make_solver(seed=3, learning_starts=10_000, demo_fraction=0.25, engine="sb3")
    solver.solve(*random_weights(np.random.default_rng(4)), 100, n_eval_episodes=1)
    solver.set_demonstrations(demos)
    sd = solver.replay_buffer.state_dict()
    assert "next_states" in sd["demo"]
    del sd["demo"]["next_states"]
    twin = make_solver(seed=3, learning_starts=10_000, demo_fraction=0.25, engine="sb3")
    twin.replay_buffer.load_state_dict(sd)
    with pytest.raises(ValueError, match="call set_demonstrations again"):
        twin.replay_buffer.set_penalty_basis(CellOccupancyCostBasis().dilated(0.2))
    twin.set_demonstrations(demos)
    twin.replay_buffer.set_penalty_basis(CellOccupancyCostBasis().dilated(0.2))


def test_an_actor_drives_the_evaluation_as_the_policy_would():
    """evaluate(actor=...) with an actor that returns the policy's mean actions from the
    joint states it is given gives the rollouts of evaluate(deterministic=True); the
    actor sees only the episodes still running and their flying agents."""
    solver = make_solver(seed=8, learning_starts=50)
    eta, wc = random_weights(np.random.default_rng(8))
    solver.solve(eta, wc, 150, n_eval_episodes=1)
    seen = []

    def actor(states, active, episodes):
        seen.append((states.shape, active.shape, tuple(episodes)))
        return solver.act(joint_obs_from_states(states), deterministic=True)

    for true_game in (False, True):
        plain = solver.evaluate(3, deterministic=True, true_game=true_game,
                                rng=np.random.default_rng(0), trajectories=True)
        acted = solver.evaluate(3, true_game=true_game, rng=np.random.default_rng(0),
                                trajectories=True, actor=actor)
        for a, b in zip(plain.paths, acted.paths, strict=True):
            np.testing.assert_array_equal(a, b)
        assert torch.equal(plain.reached, acted.reached)
        assert torch.equal(plain.violated, acted.violated)
        torch.testing.assert_close(plain.reward_sums, acted.reward_sums)
    assert seen[0] == ((3, 2, 4), (3, 2), (0, 1, 2))
    assert all(len(eps) == n[0] == m[0] for n, m, eps in seen)


@pytest.mark.parametrize("engine", ENGINES)
def test_progress_bars_count_every_step_and_change_no_number(monkeypatch, engine):
    """The warm-up's and the planned evaluation's bars (solve/solve_keeping_best/
    evaluate with progress=...) reach their totals and leave the networks, the scores
    and the rollouts those of the same calls without them."""
    import contextlib

    from dicrl_torch.solvers.sac import lineages as lineages_module
    from dicrl_torch.solvers.sac import solver as solver_module

    bars = []

    class Recorder:
        def __init__(self, label, total):
            self.label, self.total, self.n = label, total, 0

        def update(self, k):
            self.n += k

        def set_postfix(self, **kwargs):
            pass

    @contextlib.contextmanager
    def recording_bar(label, total):
        bars.append(Recorder(label, total) if label is not None else None)
        yield bars[-1]

    # the bar of solve() and that of the lineages (solver.py imports it by name)
    monkeypatch.setattr(lineages_module, "step_bar", recording_bar)
    monkeypatch.setattr(solver_module, "step_bar", recording_bar)
    eta, wc = random_weights(np.random.default_rng(9))
    plain, shown = (make_solver(seed=9, learning_starts=50, engine=engine) for _ in range(2))
    a = plain.solve(eta, wc, 120, n_eval_episodes=2)
    b = shown.solve(eta, wc, 120, n_eval_episodes=2, progress="warm-up")
    torch.testing.assert_close(a.reward_sums, b.reward_sums, rtol=0, atol=0)
    plain.solve_keeping_best(eta, wc, 60, checks=2, restarts=2, n_eval_episodes=2)
    shown.solve_keeping_best(eta, wc, 60, checks=2, restarts=2, n_eval_episodes=2,
                             progress="lineages")
    assert [(bar.label, bar.total, bar.n) for bar in bars if bar is not None] == [
        ("warm-up", 120, 120), ("lineages", 120, 120)]
    assert [c["penalised_return"] for c in plain.last_checks] == \
        [c["penalised_return"] for c in shown.last_checks]
    assert plain.n_updates > 0
    assert_same_networks(plain.policy_state(), shown.policy_state())
    x = plain.evaluate(3, true_game=True, rng=np.random.default_rng(1), trajectories=True)
    y = shown.evaluate(3, true_game=True, rng=np.random.default_rng(1), trajectories=True,
                       progress="planning")
    for p, q in zip(x.paths, y.paths, strict=True):
        np.testing.assert_array_equal(p, q)


@pytest.mark.parametrize("engine", ENGINES)
def test_lineages_split_over_equal_solvers_give_solve_keeping_best(engine):
    """Two equal solvers train lineages {0, 1} and {2} of one solve_keeping_best; the
    first adopts the best of all three (the other's read back through torch.save with
    weights_only) and is then the solver that trained all three itself: policy, scores,
    and the next solve."""
    import io

    eta, wc = random_weights(np.random.default_rng(11))
    whole, first, second = (make_solver(seed=THIRD_WINS[engine], learning_starts=50,
                                        engine=engine) for _ in range(3))
    for solver in (whole, first, second):
        solver._train(eta, wc, 60)
    kwargs = dict(checks=2, restarts=3, n_eval_episodes=2, deterministic=True)
    best = whole.solve_keeping_best(eta, wc, 60, **kwargs)
    mine = first.train_lineages(eta, wc, 60, lineages=[1, 0], **kwargs)
    theirs = second.train_lineages(eta, wc, 60, lineages=[2], **kwargs)
    assert [lineage.restart for lineage in mine] == [0, 1]
    buffer = io.BytesIO()
    torch.save(theirs[0].state(), buffer)
    buffer.seek(0)
    read = Lineage.from_state(torch.load(buffer, weights_only=True))
    adopted = first.adopt_best([*mine, read])
    assert first.last_checks == whole.last_checks
    top = max(whole.last_checks, key=lambda c: c["penalised_return"])
    assert adopted.restart == top["restart"] == 2  # (this seed) the other process's
    assert adopted.key[1] == pytest.approx(best.penalised_return()[0], rel=0, abs=0)
    assert_same_networks(whole.policy_state(), first.policy_state())
    a, b = whole.solve(eta, wc, 40, n_eval_episodes=2), first.solve(eta, wc, 40,
                                                                    n_eval_episodes=2)
    torch.testing.assert_close(a.reward_sums, b.reward_sums, rtol=0, atol=0)
    with pytest.raises(ValueError, match="distinct ints"):
        first.train_lineages(eta, wc, 60, lineages=[3], **kwargs)
    with pytest.raises(ValueError, match="distinct lineages"):
        first.adopt_best([*mine, *mine])
