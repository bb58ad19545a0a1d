"""The lean engine's SAC update (solvers/sac/update.py) against SB3's: the same weights,
batch and random draws give the same next weights, and an ensemble of learners gives
each learner exactly its own update."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dicrl_torch.envs.drones import JointDroneEnv
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.solvers.sac import SACConstrainedSolver
from dicrl_torch.solvers.sac.update import Batch, EnsembleSAC, FusedAdam

B, N_DEMO = 64, 16


def sb3_solver(**kwargs) -> SACConstrainedSolver:
    return SACConstrainedSolver(env_factory=JointDroneEnv, reward_basis=DoorLocationRewardBasis(),
                                cost_basis=CellOccupancyCostBasis(), seed=0, engine="sb3",
                                ent_coef=0.1, tau=0.02, learning_rate=1e-3, **kwargs)


def ensemble_like(policy: torch.nn.Module, n_rewards: int, **kwargs) -> EnsembleSAC:
    """An :class:`EnsembleSAC` of one learner holding SB3 ``policy``'s weights."""
    sac = EnsembleSAC(obs_dim=20, action_dim=4, hidden=(64, 64), n_rewards=n_rewards,
                      generators=[torch.Generator().manual_seed(0)], learning_rate=1e-3,
                      gamma=0.99, ent_coef=0.1, tau=0.02, **kwargs)
    sd = policy.state_dict()

    def w(key: str) -> torch.Tensor:  # nn.Linear's [out, in] as our [in, out]
        return sd[key].T

    actor = [w("actor.latent_pi.0.weight"), sd["actor.latent_pi.0.bias"][None],
             w("actor.latent_pi.2.weight"), sd["actor.latent_pi.2.bias"][None],
             torch.cat([w("actor.mu.weight"), w("actor.log_std.weight")], 1),
             torch.cat([sd["actor.mu.bias"], sd["actor.log_std.bias"]])[None]]

    def critic(prefix: str) -> list[torch.Tensor]:
        out = []
        for layer in (0, 2, 4):
            out += [torch.stack([w(f"{prefix}.qf{k}.{layer}.weight") for k in (0, 1)]),
                    torch.stack([sd[f"{prefix}.qf{k}.{layer}.bias"][None] for k in (0, 1)])]
        return out

    with torch.no_grad():
        for p, v in zip(sac.actor.params, actor, strict=True):
            p.copy_(v[None] if v.dim() == 2 else v)
        for p, v in zip(sac.critic.params, critic("critic"), strict=True):
            p.copy_(v)
        for p, v in zip(sac.target, critic("critic_target"), strict=True):
            p.copy_(v)
    return sac


@pytest.mark.parametrize("kwargs", [
    {"per_agent_critics": True, "split_cost_critic": True},  # G = 4
    {"per_agent_critics": True, "demo_fraction": 0.25, "demo_bc": 0.5,
     "demo_value_bound": True},  # G = 2, both demonstration terms
])
def test_an_update_is_sb3s_update(kwargs, monkeypatch):
    solver = sb3_solver(batch_size=B, **kwargs)
    model = solver.engine.model
    n_rewards = model.policy.n_rewards
    demo = "demo_bc" in kwargs
    sac = ensemble_like(model.policy, n_rewards, demo_bc=kwargs.get("demo_bc", 0.0),
                        demo_value_bound=kwargs.get("demo_value_bound", False))
    g = torch.Generator().manual_seed(1)
    obs, next_obs = torch.rand(B, 20, generator=g) * 4 - 2, torch.rand(B, 20, generator=g) * 4 - 2
    actions = torch.rand(B, 4, generator=g) * 2 - 1
    rewards = torch.randn(B, n_rewards, generator=g)
    dones = (torch.rand(B, 1, generator=g) < 0.2).float()
    returns = torch.randn(N_DEMO, n_rewards, generator=g) + 5.0  # some above Q, some below
    from stable_baselines3.common.type_aliases import ReplayBufferSamples

    buffer = model.replay_buffer
    monkeypatch.setattr(buffer, "sample", lambda *a, **k: ReplayBufferSamples(
        obs, actions, next_obs, dones, rewards))
    monkeypatch.setattr(buffer, "demo_rows", lambda batch: N_DEMO if demo else 0)
    monkeypatch.setattr(buffer, "sampled_demo_returns", lambda: returns)
    # SB3 draws the policy's noise at s, then at s', from the global stream.
    torch.manual_seed(7)
    noise = torch.stack([torch.empty(B, 4).normal_(), torch.empty(B, 4).normal_()])
    torch.manual_seed(7)
    model.train(gradient_steps=1, batch_size=B)
    sac.update(Batch(obs[None], actions[None], rewards[None], next_obs[None], dones[None],
                     n_demo=N_DEMO if demo else 0, demo_returns=returns[None]), noise[None])

    mine = ensemble_like(model.policy, n_rewards)  # SB3's weights after its update
    # The two compute the same formulas in another order (one head of 2 d_a outputs,
    # batched products, another reduction order): float32 rounding apart, no more.
    for ours, theirs in ((sac.actor.params, mine.actor.params),
                         (sac.critic.params, mine.critic.params), (sac.target, mine.target)):
        for p, q in zip(ours, theirs, strict=True):
            assert torch.allclose(p, q, rtol=1e-4, atol=1e-6), (p - q).abs().max()
    # ... and the update moved them (the comparison is not of two untouched networks)
    before = ensemble_like(sb3_solver(batch_size=B, **kwargs).engine.model.policy, n_rewards)
    assert any(not torch.allclose(p, q) for p, q in zip(sac.actor.params,
                                                          before.actor.params, strict=True))


def test_an_ensemble_gives_each_learner_its_own_update_bit_for_bit():
    def make(seeds):
        return EnsembleSAC(obs_dim=6, action_dim=2, hidden=(16, 16), n_rewards=2,
                           generators=[torch.Generator().manual_seed(s) for s in seeds],
                           learning_rate=1e-3, gamma=0.9, ent_coef=0.2, tau=0.05, demo_bc=0.5,
                           demo_value_bound=True)

    ensemble, alone = make([0, 1, 2]), [make([s]) for s in (0, 1, 2)]
    g = torch.Generator().manual_seed(3)
    for _ in range(5):
        batch = Batch(torch.randn(3, 32, 6, generator=g), torch.rand(3, 32, 2, generator=g),
                      torch.randn(3, 32, 2, generator=g), torch.randn(3, 32, 6, generator=g),
                      (torch.rand(3, 32, 1, generator=g) < 0.1).float(), n_demo=8,
                      demo_returns=torch.randn(3, 8, 2, generator=g))
        noise = torch.randn(3, 2, 32, 2, generator=g)
        ensemble.update(batch, noise)
        for e, sac in enumerate(alone):
            sac.update(Batch(*(t[e:e + 1] for t in (batch.obs, batch.actions, batch.rewards,
                                                     batch.next_obs, batch.dones)),
                             n_demo=8, demo_returns=batch.demo_returns[e:e + 1]),
                       noise[e:e + 1])
    for e, sac in enumerate(alone):
        for p, q in zip(ensemble.actor.params, sac.actor.params, strict=True):
            assert torch.equal(p[e:e + 1], q)
        for p, q in zip(ensemble.critic.params, sac.critic.params, strict=True):
            assert torch.equal(p[2 * e:2 * e + 2], q)
        for p, q in zip(ensemble.target, sac.target, strict=True):
            assert torch.equal(p[2 * e:2 * e + 2], q)
    assert not torch.equal(alone[0].actor.params[0], alone[1].actor.params[0])


def test_fused_adam_is_torchs_adam_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    mine = [torch.randn(3, 4, generator=g).requires_grad_() for _ in range(2)]
    theirs = [p.detach().clone().requires_grad_() for p in mine]
    ours, torchs = FusedAdam(mine, 1e-2), torch.optim.Adam(theirs, 1e-2, fused=True)
    for _ in range(4):
        grads = [torch.randn(3, 4, generator=g) for _ in mine]
        for p, q, gr in zip(mine, theirs, grads, strict=True):
            p.grad, q.grad = gr.clone(), gr.clone()
        ours.step()
        torchs.step()
        for p, q in zip(mine, theirs, strict=True):
            assert torch.equal(p, q)
    assert all(p.grad is None for p in mine)


def test_the_lean_loop_learns_the_drone_task_signal():
    """Trained a little on a door-seeking reward, the lean engine's policy gains reward
    (its update is not a no-op on the real loop: collection, labels, batches)."""
    solver = SACConstrainedSolver(env_factory=JointDroneEnv,
                                  reward_basis=DoorLocationRewardBasis(),
                                  cost_basis=CellOccupancyCostBasis(), seed=0, n_envs=4,
                                  learning_starts=500, batch_size=128, ent_coef=0.1,
                                  learning_rate=1e-3, n_eval_episodes=4, gradient_steps=4,
                                  tau=0.02, scale_observations=True)
    eta, wc = np.array([1.0, 1.0, 1.0, 1.0, 0.0]), np.zeros(solver.l_c)
    before = solver.solve(eta, wc, 0).mu_r.sum()
    after = solver.solve(eta, wc, 2000).mu_r.sum()
    # gradient_steps per vectorised step past learning_starts, as SB3 counts them
    assert solver.n_updates == 4 * (2000 - 500) // 4
    assert after > 1.5 * before  # a margin of learning, not a tuned amount


@pytest.mark.slow  # ~15-35 s on 2 threads; every suite test runs on 1 thread per process
@pytest.mark.parametrize("learners", [1, 2])
def test_the_numbers_do_not_depend_on_torchs_thread_count(learners):
    """At table2_quick's shapes (batch 256, 64x64 networks, per-drone split critics) the
    lean loop gives the same networks on 1 and on 2 torch threads, solo and as an
    ensemble: comm=simulated (torch's default threads, the learners one ensemble) and
    comm=distributed (a thread per learner process) give the same numbers."""
    from dicrl_torch.bench import TABLE2_QUICK_DYNAMICS, TABLE2_QUICK_SOLVER
    from dicrl_torch.demos.drone_demos import make_drone_demonstrations
    from dicrl_torch.envs.drones import DroneDynamics
    from dicrl_torch.solvers.sac.lean import learn_together

    dynamics = DroneDynamics(**TABLE2_QUICK_DYNAMICS)
    demos = make_drone_demonstrations(4, rng=np.random.default_rng(0), dynamics=dynamics)
    settings = {**TABLE2_QUICK_SOLVER, "learning_starts": 300}

    def trained(threads: int) -> list[dict[str, torch.Tensor]]:
        own = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            solvers = []
            for k in range(learners):
                solver = SACConstrainedSolver(
                    env_factory=lambda constrained: JointDroneEnv(constrained=constrained,
                                                                  dynamics=dynamics),
                    reward_basis=DoorLocationRewardBasis(),
                    cost_basis=CellOccupancyCostBasis(), seed=k, n_eval_episodes=1,
                    **settings)
                solver.set_demonstrations(demos)
                solver.set_weights(np.array([1.0, 1.0, 1.0, 1.0, -5.0]),
                                   np.full(solver.l_c, 0.1))
                solvers.append(solver)
            learn_together([s.engine for s in solvers], 600)
            assert all(s.n_updates == 300 for s in solvers)
            return [s.policy_state() for s in solvers]
        finally:
            torch.set_num_threads(own)

    for one, two in zip(trained(1), trained(2), strict=True):
        assert one.keys() == two.keys()
        for key in one:
            assert torch.equal(one[key], two[key]), key
