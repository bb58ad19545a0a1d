"""The SAC-style constrained solver on a game that is not the drone arena: mpe2's
``simple_spread`` made constrained (:class:`~dicrl_torch.envs.mpe.ConstrainedSpread`),
wrapped by the generic :class:`~dicrl_torch.envs.joint.JointAgentEnv`, with the generic
continuous bases. Tiny runs (a few hundred SAC steps) on one CPU thread: the protocol,
shapes, demonstrations, clones and the exact state, not learning quality. The solver's
promises are tested on its default engine (the lean loop, through its own pieces: the
replay store's ``sample`` and ``EnsembleSAC.update``) and, where cheap, on SB3's.
"""

from __future__ import annotations

import copy
import functools
import io

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from mpe2 import simple_spread_v3
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution

from dicrl_torch.demos.continuous import ContinuousDemonstrations, record_demonstrations
from dicrl_torch.demos.mpe_experts import ViaPointController
from dicrl_torch.envs.joint import JointAgentEnv
from dicrl_torch.envs.mpe import ConstrainedSpread
from dicrl_torch.features.continuous import PositionCellBasis, RandomFourierBasis
from dicrl_torch.solvers.sac import SACConstrainedSolver, discounted_demo_feature_sums
from dicrl_torch.solvers.sac.update import Batch, EnsembleSAC

torch.set_num_threads(1)

GAMMA = 0.95
MAX_STEPS = 12
N, D_S, D_A = 2, 4, 2  # ConstrainedSpread: 2 agents, state (x, y, vx, vy), command [2]


def spread_game(constrained: bool, max_steps: int = MAX_STEPS,
                observation: str = "state") -> JointAgentEnv:
    """The solver's env_factory: the constrained simple_spread as one gymnasium env whose
    observation is the flattened joint state ``[N * 4]``."""
    return JointAgentEnv(ConstrainedSpread(constrained=constrained, max_steps=max_steps),
                         observation=observation)


def reward_basis() -> RandomFourierBasis:
    return RandomFourierBasis(n_agents=N, state_dim=D_S, n_features=6, bandwidth=1.0, seed=0)


def cost_basis() -> PositionCellBasis:
    return PositionCellBasis(n_agents=N, bounds=((-1.5, 1.5), (-1.5, 1.5)),
                             proximity_radius=0.4, n_per_axis=3, obstacle_centre=(0.0, 0.0),
                             obstacle_radius=0.3, min_distance=0.4)


L_R, L_C = 6, 3 * 3 + 1
ETA = np.array([1.0, 0.5, 0.2, 1.0, 0.3, 0.7, -1.0])  # [ω_r (6), λ]
COST = np.linspace(0.0, 1.0, L_C)


ENGINES = ("lean", "sb3")


def make_solver(seed: int = 0, **kwargs) -> SACConstrainedSolver:
    args = dict(env_factory=spread_game, reward_basis=reward_basis(), cost_basis=cost_basis(),
                seed=seed, n_envs=2, gamma=GAMMA, learning_starts=40, batch_size=16,
                buffer_size=400, net_arch=(16, 16), n_eval_episodes=3, demo_fraction=0.25)
    args.update(kwargs)
    return SACConstrainedSolver(**args)


def via_point_policy(observations, env):
    """The constrained expert of ConstrainedSpread as a record_demonstrations policy."""
    if env.timestep == 0:
        env.expert = ViaPointController(env)
        env.expert.reset(env.state())
    u = env.expert.act(env.state(), env.active)
    return {a: u[env.possible_agents.index(a)] for a in observations}


@pytest.fixture(scope="module")
def demos() -> ContinuousDemonstrations:
    # use_state=True: the joint state env.state() [N, 4], as JointAgentEnv reads it.
    return record_demonstrations(ConstrainedSpread(max_steps=MAX_STEPS), via_point_policy,
                                 n_episodes=3, seed=0, use_state=True)


def round_trip(sd: dict) -> dict:
    f = io.BytesIO()
    torch.save(sd, f)
    f.seek(0)
    return torch.load(f, weights_only=True)


def sampled_labels(solver: SACConstrainedSolver, batch_size: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A batch of stored transitions from the solver's replay buffer (no demonstrations
    set): its reward columns ``[B, G]``, and the stored ``φ_r`` ``[B, l_r]``, ``φ_c``
    ``[B, l_c]`` (float64) and absorbing scale ``[B]`` of the rows it drew."""
    buf = solver.replay_buffer
    if solver.engine.name == "sb3":
        batch = buf.sample(batch_size)  # SB3 draws from the global numpy stream
        rewards, rows = batch.rewards.numpy(), buf.last_sample_indices
    else:
        (obs, actions, rewards, _, _), demo = buf.sample(batch_size,
                                                         torch.Generator().manual_seed(0))
        assert demo is None
        # the stored rows the batch holds: the one of each sampled (o, a)
        n = buf.size
        match = ((buf.obs[:n, None] == obs[None]).all(-1)
                 & (buf.actions[:n, None] == actions[None]).all(-1))  # [n, B]
        assert (match.sum(0) == 1).all()
        rows, rewards = match.int().argmax(0).numpy(), rewards.numpy()
    return (rewards, buf.reward_features[rows].astype(np.float64),
            buf.cost_features[rows].astype(np.float64), buf.reward_scale[rows])


# ------------------------------------------------------------------ the joint env
def test_joint_agent_env_gives_what_the_solver_reads():
    env = spread_game(constrained=False)
    assert env.n_agents == N and env.state_shape == (N, D_S) and env.use_state
    obs, info = env.reset(seed=3)
    np.testing.assert_array_equal(info["state"], env.env.state())
    # observation="state": the observation is the flattened state, so states map back.
    np.testing.assert_array_equal(env.obs_from_states(info["state"]), obs)
    obs, _, _, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
    assert info["reached"].shape == (N,) and info["violated"].shape == (N,)
    assert info["reached"].dtype == bool and not info["reached"].any()  # no goal notion
    np.testing.assert_array_equal(env.obs_from_states(info["state"][None])[0], obs)
    # With the agents' observations the policy sees something no state gives back.
    agents = spread_game(constrained=False, observation="agents")
    with pytest.raises(ValueError, match="cannot rebuild its observations.*observation='state'"):
        agents.obs_from_states(info["state"])


# ------------------------------------------------------------------ solving
def test_solve_on_a_third_party_game_gives_feature_expectations_of_the_bases():
    solver = make_solver()
    assert solver.spec.n_agents == N and solver.spec.state_shape == (N, D_S)
    sol = solver.solve(ETA, COST, 300)
    assert solver.num_timesteps == 300 and solver.n_updates > 0
    assert sol.mu_r.shape == (L_R,) and sol.mu_c.shape == (L_C,)
    assert sol.reward_sums.shape == (3, L_R) and sol.cost_sums.shape == (3, L_C)
    assert sol.reached.shape == (3, N) and sol.violated.shape == (3, N)
    # The nominal game never freezes anyone: every episode runs to its limit (truncated,
    # no absorbing bonus), and each agent counts once per step in the cells' block.
    assert torch.equal(sol.lengths, torch.full((3,), MAX_STEPS))
    mass = (1 - GAMMA**MAX_STEPS) / (1 - GAMMA)
    torch.testing.assert_close(sol.cost_sums[:, :-1].sum(1),
                               torch.full((3,), N * mass, dtype=torch.float64))
    for sums, basis in ((sol.reward_sums, solver.reward_basis),
                        (sol.cost_sums, solver.cost_basis)):
        assert sums.min() >= 0 and sums.max() <= basis.max_value / (1 - GAMMA) + 1e-9
    # The true game is the factory's constrained=True game; trajectories are joint states.
    true = solver.evaluate(2, true_game=True, deterministic=True, trajectories=True)
    assert [p.shape[1:] for p in true.paths] == [(N, D_S)] * 2
    assert [len(p) for p in true.paths] == (true.lengths + 1).tolist()
    assert 0.0 <= true.violation_rate <= 1.0
    episodes = solver._eval_envs[(True, 2)]  # the game's batched env, or joint envs
    assert (episodes.vector.constrained if episodes.vector is not None
            else episodes.envs[0].env.constrained)


def test_estimates_from_mean_actions_are_the_deployed_policys_rollouts():
    sampled, mean = make_solver(), make_solver(estimate_action="mean")
    a, b = sampled.solve(ETA, COST, 200), mean.solve(ETA, COST, 200)
    p, q = sampled.policy_state(), mean.policy_state()
    for key in p:  # the rollouts do not change the training
        assert torch.equal(p[key], q[key]), key
    assert not torch.equal(a.cost_sums, b.cost_sums)
    # the same networks and fresh evaluation streams, scored with mean actions
    deployed = sampled.clone(sampled.seed).evaluate(deterministic=True)
    torch.testing.assert_close(b.cost_sums, deployed.cost_sums)
    torch.testing.assert_close(b.mu_r, deployed.mu_r)
    with pytest.raises(ValueError, match="estimate_action must be one of"):
        make_solver(estimate_action="greedy")
    sd = round_trip(mean.state_dict())
    with pytest.raises(ValueError, match="estimate_action: state 'mean'"):
        make_solver().load_state_dict(sd)


@pytest.mark.parametrize("engine", ENGINES)
def test_per_agent_critics_split_team_features_equally(engine):
    # PositionCellBasis counts the whole team per cell: no feature is one agent's own,
    # so each agent's reward column is half the joint reward.
    solver = make_solver(per_agent_critics=True, learning_starts=1000, engine=engine)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)
    rewards, phi_r, phi_c, scale = sampled_labels(solver, 16)
    assert rewards.shape == (16, N)
    # (float32 labels of float64 sums: equal to ~1e-7 relative)
    np.testing.assert_allclose(rewards.sum(1), scale * (phi_r @ ETA[:-1]
                                                       + ETA[-1] * (phi_c @ COST)),
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rewards[:, 0], rewards[:, 1], rtol=1e-6)
    # Scoring chunks by success under learned constraints uses the same shares; the
    # spread reports no goal (reached is always False), so every score is 0.
    solver.solve_keeping_best(ETA, COST, 20, checks=2, n_eval_episodes=1,
                              constraints=solver.cost_basis.true_constraints())
    assert [c["success_under_constraints"] for c in solver.last_checks] == [0.0, 0.0]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("per_agent", [False, True])
def test_split_cost_critics_sample_reward_and_cost_columns(per_agent, engine):
    """With ``split_cost_critic`` the batch holds the reward part ``ω_r·φ_r`` and the cost
    part ``λ ω_c·φ_c`` as separate columns (each per agent with per-agent critics),
    computed here from the stored features; together they are the joint reward; the
    critics have one soft-Q column per batch column."""
    solver = make_solver(split_cost_critic=True, per_agent_critics=per_agent,
                         learning_starts=1000, engine=engine)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)
    g = N if per_agent else 1
    if engine == "sb3":
        assert type(solver.engine.model).__name__ == "DecomposedSAC"
        assert solver.engine.model.critic.qf0[-1].out_features == 2 * g
    else:
        sac = solver.engine.sac
        q = sac.critic.forward_with(sac.critic.params, torch.zeros(1, 3, N * D_S),
                                    torch.zeros(1, 3, N * D_A))
        assert sac.n_rewards == 2 * g and q.shape == (1, 2, 3, 2 * g)
    rewards, phi_r, phi_c, scale = sampled_labels(solver, 16)
    assert rewards.shape == (16, 2 * g)
    # (float32 labels of float64 sums: equal to ~1e-7 relative)
    np.testing.assert_allclose(rewards[:, :g].sum(1), scale * (phi_r @ ETA[:-1]),
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rewards[:, g:].sum(1), scale * ETA[-1] * (phi_c @ COST),
                               rtol=1e-5, atol=1e-5)
    if engine == "sb3":
        b, e = solver.replay_buffer.last_sample_indices
        np.testing.assert_allclose(rewards.sum(1), solver.replay_buffer.compute_rewards(b, e),
                                   rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------ demonstrations
@pytest.mark.parametrize("engine", ENGINES)
def test_log_likelihood_and_feature_sums_of_recorded_demonstrations(demos, engine):
    solver = make_solver(seed=1, engine=engine)
    solver.set_demonstrations(demos)  # their transitions go into the SAC batches
    solver.solve(ETA, COST, 120, n_eval_episodes=1)
    per = solver.log_likelihood(demos, per_episode=True)
    assert per.shape == (3,) and per.dtype == torch.float64 and torch.isfinite(per).all()
    assert solver.log_likelihood(demos) == pytest.approx(float(per.sum()))
    # The first step alone against SB3's own squashed density of the joint action at the
    # actor's outputs (the expert's saturated commands clipped to ±(1 - action_margin)
    # first, as the solver does: SB3 clips at float32's epsilon instead).
    obs = torch.from_numpy(demos.states[:, 0].reshape(3, -1).astype(np.float32))
    act = torch.from_numpy(np.clip(demos.actions[:, 0].reshape(3, -1), -0.999, 0.999)
                           .astype(np.float32))
    with torch.no_grad():
        if engine == "sb3":
            actor = solver.engine.model.actor
            mean, log_std, _ = actor.get_action_dist_params(obs)
        else:  # the observation is the state (scale_observations=False: as it is)
            mean, log_std = (x[0] for x in solver.engine.sac.actor.dist_params(obs[None]))
        sb3 = SquashedDiagGaussianDistribution(N * D_A).proba_distribution(
            mean, log_std).log_prob(act)
    one = ContinuousDemonstrations(states=demos.states[:, :2], actions=demos.actions[:, :1],
                                   lengths=np.ones(3, np.int64))
    # (float32 in SB3 near the clip: agreement to ~1e-4 relative)
    torch.testing.assert_close(solver.log_likelihood(one, per_episode=True), sb3.double(),
                               rtol=1e-3, atol=1e-3)
    # An agent's actions after it left the episode are not scored.
    acted = np.array(demos.lengths)[:, None].repeat(N, 1)
    acted[:, 1] = 2
    other = np.array(demos.actions)
    other[:, 2:, 1] = 0.5
    left = [ContinuousDemonstrations(states=demos.states, actions=a, lengths=demos.lengths,
                                     agent_lengths=acted) for a in (demos.actions, other)]
    assert solver.log_likelihood(left[0]) == solver.log_likelihood(left[1])
    assert solver.log_likelihood(left[0]) != solver.log_likelihood(demos)
    # Feature sums as the solver counts rollouts: next states, absorbing last state.
    sums = discounted_demo_feature_sums(demos, solver.cost_basis, GAMMA)
    L = int(demos.lengths[0])
    w = GAMMA ** torch.arange(L, dtype=torch.float64)
    w[-1] /= 1 - GAMMA
    torch.testing.assert_close(sums[0], w @ solver.cost_basis(demos.states[0, 1:L + 1]))


def test_demonstrations_of_other_shapes_are_refused_naming_field_and_fix(demos):
    solver = make_solver()
    fewer = ContinuousDemonstrations(states=demos.states[..., :3], actions=demos.actions,
                                     lengths=demos.lengths)
    with pytest.raises(ValueError, match=r"field 'states'.*\[2, 3\].*\[2, 4\].*use_state"):
        solver.log_likelihood(fewer)
    wider = ContinuousDemonstrations(states=demos.states, lengths=demos.lengths,
                                     actions=np.concatenate([demos.actions] * 2, -1))
    with pytest.raises(ValueError, match=r"field 'actions'.*8 values.*has 4"):
        solver.set_demonstrations(wider)
    one_agent = ContinuousDemonstrations(states=demos.states[:, :, :1],
                                         actions=demos.actions[:, :, :1],
                                         lengths=demos.lengths)
    with pytest.raises(ValueError, match="field 'states'"):
        solver.log_likelihood(one_agent)
    with pytest.raises(ValueError, match="ContinuousDemonstrations"):
        solver.log_likelihood(np.zeros((3, 5, 2, 4)))
    # An env whose observation is not the state cannot score demonstrations.
    agents = make_solver(env_factory=functools.partial(spread_game, observation="agents"))
    with pytest.raises(ValueError, match="cannot rebuild its observations"):
        agents.log_likelihood(demos)


# ------------------------------------------------------------------ refusals
class DiscreteGame(gym.Env):
    """A one-agent gymnasium game with discrete actions."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Discrete(3)
    n_agents, state_shape = 1, (1, 2)

    def __init__(self, constrained: bool = False) -> None:
        self.constrained = constrained


def test_discrete_action_games_are_refused_with_the_fix():
    def discrete_spread(constrained):
        return JointAgentEnv(simple_spread_v3.parallel_env(N=2, continuous_actions=False))

    with pytest.raises(ValueError, match=r"Discrete\(5\).*continuous_actions=True"):
        make_solver(env_factory=discrete_spread)
    with pytest.raises(ValueError, match=r"DiscreteGame has the action space Discrete\(3\); "
                                         r"the SAC solver needs continuous actions"):
        make_solver(env_factory=DiscreteGame)
    with pytest.raises(ValueError, match="not a gymnasium env.*JointAgentEnv"):
        make_solver(env_factory=lambda constrained: ConstrainedSpread(constrained=constrained))
    with pytest.raises(ValueError, match="keyword constrained"):
        make_solver(env_factory=lambda: spread_game(False))


# ------------------------------------------------------------------ clones and state
def slot_rng(solver: SACConstrainedSolver) -> np.random.Generator:
    """The noise stream of the first training env slot."""
    if solver.engine.name == "sb3":
        return solver.engine.vec_env.envs[0].unwrapped.env._rng
    return solver.engine.vec._rngs[0]  # the spread's own batched env


@pytest.mark.parametrize("engine", ENGINES)
def test_clone_gets_its_own_streams_and_the_state_round_trips(demos, engine):
    solver = make_solver(seed=2, engine=engine)
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 90, n_eval_episodes=1)  # episodes of 12 cut mid-way
    twin = solver.clone(9)
    rngs = [slot_rng(s) for s in (solver, twin)]
    assert rngs[0] is not rngs[1]  # set_rng: the twin's own noise stream
    assert rngs[0].bit_generator.state != rngs[1].bit_generator.state
    a = twin.solve(ETA, COST, 60, n_eval_episodes=2)
    assert a.mu_c.shape == (L_C,)

    # The exact state: saved mid-episode, loaded into a fresh solver built with the same
    # arguments (but another seed: the state carries the seed), continued identically.
    sd = round_trip(solver.state_dict())
    back = make_solver(seed=5, engine=engine)
    back.load_state_dict(sd)
    for s in (solver, back):
        s.set_weights(ETA * 0.5, COST)
    ref, got = solver.solve(ETA * 0.5, COST, 70), back.solve(ETA * 0.5, COST, 70)
    for name in ("reward_sums", "cost_sums", "lengths", "reached", "violated"):
        assert torch.equal(getattr(ref, name), getattr(got, name)), name
    mine, theirs = solver.policy_state(), back.policy_state()
    assert mine.keys() == theirs.keys()
    for key, value in mine.items():
        assert torch.equal(value, theirs[key]), key
    assert solver.log_likelihood(demos) == back.log_likelihood(demos)
    # A state of another game (other spaces) is refused, naming the difference.
    with pytest.raises(ValueError, match="env: state"):
        make_solver(env_factory=functools.partial(spread_game, observation="agents"),
                    engine=engine).load_state_dict(sd)


# ------------------------------------------------ the Q-filtered demonstration loss
def lean_batch(solver: SACConstrainedSolver, batch_size: int, generator: torch.Generator,
               returns: float | None = None) -> Batch:
    """A batch of the lean engine's replay store as its update takes it (one learner);
    with ``returns``, every demonstrated transition's return set to it first."""
    store = solver.replay_buffer
    if returns is not None:
        store._demo_returns = np.full((len(store._demo["dones"]), store.n_rewards), returns)
    (obs, actions, rewards, next_obs, dones), demo_idx = store.sample(batch_size, generator)
    n_demo = 0 if demo_idx is None else len(demo_idx)
    return Batch(obs=obs[None], actions=actions[None], rewards=rewards[None],
                 next_obs=next_obs[None], dones=dones[None], n_demo=n_demo,
                 demo_returns=None if returns is None
                 else store.demo_returns_of(demo_idx)[None])


def updated(sac: EnsembleSAC, batch: Batch, noise: torch.Tensor, **settings: object
            ) -> tuple[EnsembleSAC, list[torch.Tensor]]:
    """A copy of ``sac`` with ``settings``, after one update on ``batch`` with ``noise``,
    and the actor's gradients that update stepped on."""
    sac = copy.deepcopy(sac)
    for name, value in settings.items():
        setattr(sac, name, value)
    grads, step = [], sac.actor_optimizer.step

    def recording_step() -> None:
        grads.extend(p.grad.clone() for p in sac.actor.params)
        step()

    sac.actor_optimizer.step = recording_step
    sac.update(batch, noise)
    return sac, grads


def test_demo_loss_acts_only_where_the_critic_prefers_the_demonstrated_action(demos):
    """The lean engine's update with the Q-filtered demonstration loss against one without
    it, on the same batch and noise: the critics step alike (the loss reaches the actor
    only), and the actor's gradients differ by that of the formula computed here from
    the actor and the stepped critics: rows whose demonstrated action the critic rates
    lower contribute nothing, the others ``||tanh μ(s) − a||²``, scaled by
    ``demo_bc · mean|Q(s, π(s))|``."""
    solver = make_solver(demo_bc=0.5)
    sac = solver.engine.sac
    assert sac.demo_bc == 0.5
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)  # networks past their initialisation
    batch_size, patterns = 16, []
    noise = torch.randn((1, 2, batch_size, N * D_A), generator=torch.Generator().manual_seed(1))
    for seed in range(6):  # batches where the critic prefers none, some, ... of the rows
        batch = lean_batch(solver, batch_size, torch.Generator().manual_seed(seed))
        n_demo = batch.n_demo
        assert n_demo == 4  # round(0.25 * 16), the batch's last rows
        obs, demo_actions = batch.obs[0], batch.actions[0, -n_demo:]
        with_loss, grads = updated(sac, batch, noise)
        plain, plain_grads = updated(sac, batch, noise, demo_bc=0.0)
        for a, b in zip(with_loss.critic.params + with_loss.target,
                        plain.critic.params + plain.target, strict=True):
            assert torch.equal(a, b)

        # The formula, from the actor before the update and the critics it stepped against.
        actor = copy.deepcopy(sac.actor)
        mean, log_std = actor.dist_params(obs[None])
        actions_pi = torch.tanh(mean + noise[:, 0] * log_std.exp())  # the batch's π(s)
        critic = with_loss.critic
        with torch.no_grad():
            q_pi = critic.forward_with(critic.params, obs[None], actions_pi).amin(1)[0, :, 0]
            q_demo = critic.forward_with(critic.params, obs[None, -n_demo:],
                                         demo_actions[None]).amin(1)[0, :, 0]
        better = q_demo > q_pi[-n_demo:]
        patterns.append(tuple(better.tolist()))
        gap = ((torch.tanh(mean[0, -n_demo:]) - demo_actions) ** 2).sum(-1)
        want = 0.5 * q_pi.abs().mean() * (better * gap).mean()
        # the engine's term on these inputs is the formula's value
        loss = sac._demo_loss(mean[:, -n_demo:], q_demo[None], q_pi[None, :, None], batch)
        assert torch.allclose(loss, want, rtol=1e-5, atol=1e-7)
        if not better.any():  # no pull at all: the very update without the term
            for g, g0 in zip(grads, plain_grads, strict=True):
                assert torch.equal(g, g0)
            continue
        want.backward()
        for p, g, g0 in zip(actor.params, grads, plain_grads, strict=True):
            # (the actor's gradient with the term minus without it: float32 sums of
            # different terms, equal to rounding)
            torch.testing.assert_close(g - g0, p.grad, rtol=1e-5, atol=1e-7)
        assert any(not torch.equal(g, g0) for g, g0 in zip(grads, plain_grads, strict=True))
        # A critic that rates every demonstrated action lower: no pull at all.
        q_high = q_pi[None, :, None] + 1e6
        assert float(sac._demo_loss(mean[:, -n_demo:], q_demo[None], q_high,
                                    batch).detach()) == 0.0
    # both cases met: rows the critic prefers mixed with others, and none preferred
    assert any(0 < sum(b) < len(b) for b in patterns) and (False,) * 4 in patterns, patterns


def test_sb3_demo_loss_acts_only_where_the_critic_prefers_the_demonstrated_action(demos):
    """``DecomposedSAC._demo_loss`` (SB3's engine) against its formula computed here from
    the actor and critic: rows whose demonstrated action the critic rates lower
    contribute nothing, the others ``||tanh μ(s) − a||²``, scaled by
    ``demo_bc · mean|Q(s, π(s))|``; its gradient reaches the actor only."""
    solver = make_solver(demo_bc=0.5, engine="sb3")
    model = solver.engine.model
    assert type(model).__name__ == "DecomposedSAC" and model.demo_bc == 0.5
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)  # networks past their initialisation
    batch = 16
    n_demo = model.replay_buffer.demo_rows(batch)
    assert n_demo == 4  # round(0.25 * 16), the batch's last rows
    data = model.replay_buffer.sample(batch)
    actions_pi, _ = model.actor.action_log_prob(data.observations)
    q_pi = torch.stack(model.critic(data.observations, actions_pi)).amin(0).detach()  # [B, 1]
    obs, demo_actions = data.observations[-n_demo:], data.actions[-n_demo:]
    with torch.no_grad():
        q_demo = torch.stack(model.critic(obs, demo_actions)).amin(0)[:, 0]
        mean_actions = torch.tanh(model.actor.get_action_dist_params(obs)[0])
    better = q_demo > q_pi[-n_demo:, 0]
    want = 0.5 * q_pi.abs().mean() * (better * ((mean_actions - demo_actions) ** 2).sum(-1)
                                      ).mean()
    model._demo_accept = []
    loss = model._demo_loss(data, q_pi)
    assert torch.allclose(loss, want, rtol=1e-5, atol=1e-7)
    assert float(model._demo_accept[0]) == pytest.approx(float(better.float().mean()))
    model.actor.zero_grad(), model.critic.zero_grad()
    loss.backward()
    assert all(p.grad is None or not p.grad.any() for p in model.critic.parameters())
    if better.any():
        assert any(p.grad is not None and p.grad.any() for p in model.actor.parameters())
    # A critic that rates every demonstrated action lower: no pull at all.
    q_high = q_pi + 1e6
    model._demo_accept = []
    assert float(model._demo_loss(data, q_high).detach()) == 0.0


def test_demo_loss_settings_are_checked_and_saved(demos):
    with pytest.raises(ValueError, match="demo_bc=0.5 acts on the demonstrated rows.*"
                                         "demo_fraction > 0"):
        make_solver(demo_bc=0.5, demo_fraction=0.0)
    with pytest.raises(ValueError, match="demo_bc must be a finite number >= 0"):
        make_solver(demo_bc=-1.0)
    with_loss = make_solver(demo_bc=0.5)
    with_loss.set_demonstrations(demos)
    with_loss.solve(ETA, COST, 50, n_eval_episodes=1)
    sd = round_trip(with_loss.state_dict())
    with pytest.raises(ValueError, match="demo_bc: state 0.5, this solver 0.0"):
        make_solver().load_state_dict(sd)
    # A state saved before the setting existed had no demonstration loss.
    plain = make_solver()
    old = plain.state_dict()
    del old["settings"]["demo_bc"]
    plain.load_state_dict(round_trip(old))


def test_demo_returns_are_each_episodes_discounted_learned_return(demos):
    """``FeatureReplayBuffer.demo_returns`` against a direct sum over each recorded
    episode of ``γ^k r(s_{t+k+1})``, with ``r = ω_r·φ_r + λ ω_c·φ_c`` from the bases."""
    solver = make_solver(demo_value_bound=True)
    solver.set_demonstrations(demos)
    solver.set_weights(ETA, COST)
    got = solver.replay_buffer.demo_returns()  # [n, 1]
    want = []
    for e in range(demos.n_episodes):
        nxt = torch.tensor(demos.states[e, 1:demos.lengths[e] + 1], dtype=torch.float64)
        r = (solver.reward_basis(nxt).double().numpy() @ ETA[:-1]
             + ETA[-1] * solver.cost_basis(nxt).double().numpy() @ COST)
        if solver.absorbing:  # the last state is absorbing: its reward for ever
            r[-1] /= 1 - GAMMA
        want += [sum(GAMMA ** k * r[t + k] for k in range(len(r) - t)) for t in range(len(r))]
    np.testing.assert_allclose(got[:, 0], want, rtol=1e-5)
    # New weights, new returns.
    solver.set_weights(ETA * 2, COST)
    np.testing.assert_allclose(solver.replay_buffer.demo_returns()[:, 0], 2 * np.array(want),
                               rtol=1e-5)


def test_the_value_bound_lifts_the_critic_only_below_the_demonstrated_returns(demos):
    """The lean engine's updates with the bound move Q(s, a_demo) up towards returns above
    it; with returns far below Q the bound is inactive and the updates are plain SAC's
    (the same batches and noise with it and without)."""
    solver = make_solver(demo_value_bound=True, demo_fraction=0.5)
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)
    sac, d = solver.engine.sac, solver.replay_buffer._demo_torch
    assert sac.demo_value_bound

    def q_demo(s: EnsembleSAC) -> torch.Tensor:
        with torch.no_grad():
            return s.critic.forward_with(s.critic.params, d["obs"][None],
                                         d["actions"][None]).amin(1)[0].sum(-1)

    def train_pair(returns: float, steps: int) -> tuple[EnsembleSAC, EnsembleSAC]:
        """Copies of the SAC after the same updates, with the bound and without."""
        pair = []
        for bound in (True, False):
            s = copy.deepcopy(sac)
            s.demo_value_bound = bound
            gen = torch.Generator().manual_seed(3)
            for _ in range(steps):
                batch = lean_batch(solver, 16, gen, returns)
                assert batch.n_demo == 8
                s.update(batch, torch.randn((1, 2, 16, N * D_A), generator=gen))
            pair.append(s)
        return pair[0], pair[1]

    # Returns far above Q: the bound lifts Q(s, a_demo) beyond what plain SAC gives.
    bound, plain = train_pair(1e3, 30)
    assert float((q_demo(bound) - q_demo(plain)).mean()) > 0
    # Returns far below every Q: the bound is inactive, the updates are plain SAC's.
    bound, plain = train_pair(-1e9, 5)
    for a, b in zip(bound.critic.params + bound.actor.params,
                    plain.critic.params + plain.actor.params, strict=True):
        assert torch.equal(a, b)


def test_sb3_value_bound_lifts_the_critic_only_below_the_demonstrated_returns(demos):
    """As above through SB3's engine (``DecomposedSAC.train``)."""
    solver = make_solver(demo_value_bound=True, demo_fraction=0.5, engine="sb3")
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 60, n_eval_episodes=1)
    model = solver.engine.model
    buffer = model.replay_buffer
    d = buffer._demo
    obs = torch.as_tensor(buffer._normalize_obs(d["obs"], None))
    acts = torch.as_tensor(d["actions"])

    def q_demo(m):
        with torch.no_grad():
            return torch.stack(m.critic(obs, acts)).amin(0)[:, 0]

    def train_pair(returns: float, steps: int) -> SACConstrainedSolver:
        """The same updates (same random numbers) with the bound and without (a clone);
        the clone is returned."""
        twin = solver.clone(seed=7)
        for s, bound in ((solver, True), (twin, False)):
            s.engine.model.demo_value_bound = bound
            s.replay_buffer._demo_returns = np.full((len(acts), 1), returns)
            torch.manual_seed(3), np.random.seed(3)  # noqa: NPY002 (SB3's stream)
            s.engine.model.train(gradient_steps=steps, batch_size=16)
        return twin

    # Returns far above Q: the bound lifts Q(s, a_demo) beyond what plain SAC gives.
    twin = train_pair(1e3, 30)
    assert float((q_demo(solver.engine.model) - q_demo(twin.engine.model)).mean()) > 0
    # Returns far below every Q: the bound is inactive, the updates are plain SAC's.
    twin = train_pair(-1e9, 5)
    for a, b in zip(solver.engine.model.critic.parameters(),
                    twin.engine.model.critic.parameters(), strict=True):
        assert torch.equal(a, b)


def old_sb3_state(sd: dict) -> dict:
    """An ``engine="sb3"`` solver's state in the layout of states saved before the engines
    ("/2"): SB3's pieces at the top, no engine among the settings."""
    assert sd["settings"]["engine"] == "sb3"
    old = {k: v for k, v in sd.items() if k != "engine"}
    return {**old, **sd["engine"], "format": "dicrl_torch.SACConstrainedSolver/2",
            "settings": {k: v for k, v in sd["settings"].items() if k != "engine"}}


def test_a_demonstrated_time_limit_end_is_a_truncation_and_old_states_load(demos):
    """The spread has no absorbing goal: its demonstrations end at the time limit, which
    SAC bootstraps past (done 0), while the episode boundaries are kept for the returns
    (both engines). States saved before the engines load into an SB3 solver, also one
    whose buffer was saved before the boundaries were stored ("ends")."""
    for engine in ENGINES:
        solver = make_solver(absorbing=False, engine=engine)
        solver.set_demonstrations(demos)
        d = solver.replay_buffer._demo
        assert not d["dones"].any() and int(d["ends"].sum()) == demos.n_episodes
        if engine == "lean":  # what its batches gather
            assert not solver.replay_buffer._demo_torch["dones"].any()
        absorbing = make_solver(absorbing=True, engine=engine)
        absorbing.set_demonstrations(demos)
        np.testing.assert_array_equal(absorbing.replay_buffer._demo["dones"],
                                      absorbing.replay_buffer._demo["ends"].astype(np.float32))

    solver = make_solver(absorbing=False, engine="sb3")
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 30, n_eval_episodes=1)
    returns = solver.replay_buffer.demo_returns()
    old = round_trip(old_sb3_state(solver.state_dict()))
    again = make_solver(absorbing=False, engine="sb3", seed=4)
    again.load_state_dict(old)
    assert again.seed == 0 and again.num_timesteps == 30
    np.testing.assert_array_equal(again.replay_buffer.demo_returns(), returns)
    mine, theirs = solver.policy_state(), again.policy_state()
    for key, value in mine.items():
        assert torch.equal(value, theirs[key]), key
    # it continues as the solver that saved it
    ref, got = (s.solve(ETA, COST, 10, n_eval_episodes=1) for s in (solver, again))
    for name in ("reward_sums", "cost_sums", "lengths"):
        assert torch.equal(getattr(ref, name), getattr(got, name)), name
    with pytest.raises(ValueError, match="engine: state 'sb3', this solver 'lean'"):
        make_solver(absorbing=False).load_state_dict(old)

    del old["replay_buffer"]["demo"]["ends"]
    again = make_solver(absorbing=False, engine="sb3")
    again.load_state_dict(old)
    again.set_weights(ETA, COST)
    # the old state's dones (all 0 here) stand in for the ends: one long "episode"
    assert again.replay_buffer._demo["ends"].dtype == bool
    assert not again.replay_buffer._demo["ends"].any()
    assert again.replay_buffer.demo_returns().shape == returns.shape
