"""SAC with a reward-decomposed critic: one soft-Q column per agent.

The joint reward of a team is a sum of per-agent parts, ``r = Σ_g r_g``
(:class:`~dicrl_torch.solvers.sac.FeatureReplayBuffer` with ``per_agent=True`` samples
them as ``[B, G]``, from the bases' ``agent_shares()``; a shared feature such as a
proximity is split equally). Each critic here outputs ``[B, G]`` and column ``g`` is
trained on its own part,

    Q_g(s, a) = r_g + γ E[Q_g(s', a') − (α / G) ln π(a' | s')],

so ``Σ_g Q_g`` satisfies the joint soft Bellman equation: the fixed point, and the actor's
objective ``E[α ln π(a | s) − Σ_g Q_g(s, a)]``, are plain SAC's. What changes is the
regression, and the intent is an easier one: one agent's return is no longer noise in the
target of the others'. (In a controlled check on the paper's Table 2 game it did not stop
SAC's swings between behaviours; see the Table 2 notes in docs/.) The twin-critic minimum
is taken per column (a lower bound of the minimum of the sums).

With ``G = 1`` :meth:`DecomposedSAC.train` is SB3's ``SAC.train`` for a fixed temperature
(``tests/test_sac_solver.py`` compares their updates).

**Q-filtered demonstration loss** (``demo_bc > 0``; Nair et al. 2018, "Overcoming
exploration in RL with demonstrations"). On the batch rows drawn from the learner's own
demonstrations (the replay buffer's ``demo_fraction``) the actor also pays

    demo_bc · mean|Q(s, π(s))| · 1[Q(s, a_demo) > Q(s, π(s))] · ||tanh μ(s) − a_demo||²,

pulling its mean action towards a demonstrated one only where its own critic rates the
demonstrated action higher than the policy's. Where the policy's action is rated at least
as high the term is 0, so at the soft-optimal policy of the learned game it vanishes and
the fixed point is SAC's; what it changes is how that fixed point is found: coordinated
manoeuvres (one agent yielding to the other) that random exploration rarely strings
together. The ``mean|Q|`` factor makes ``demo_bc`` free of the reward's scale (as
TD3+BC's normalisation).

**Demonstrated returns as a lower bound of the critic** (``demo_value_bound``). A
demonstrated action followed by the rest of its demonstration earns the discounted
return ``G_t`` of the learned reward (:meth:`FeatureReplayBuffer.demo_returns`), so the
optimal ``Q(s_t, a_t) >= G_t``; the critics also pay ``0.5 relu(G_t − Q_k(s_t, a_t))²`` on
the demonstrated rows (self-imitation's bound, Oh et al. 2018). One-step targets carry a
coordinated manoeuvre's value back only as far as the policy already follows it; the
bound gives its whole value at once, and it is inactive wherever the critic already
rates the demonstration at least that high, so the fixed point is unchanged.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, create_mlp
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

__all__ = ["DecomposedCritic", "DecomposedSAC", "DecomposedSACPolicy",
           "squashed_gaussian_sample"]

_SQUASH_EPSILON = 1e-6  # SB3's SquashedDiagGaussianDistribution epsilon


def _polyak(params: list[torch.Tensor], targets: list[torch.Tensor], tau: float) -> None:
    """SB3's ``polyak_update`` (``target ← (1 − τ) target + τ param``, the same two
    operations, so the same bits) on all tensors at once."""
    with torch.no_grad():
        torch._foreach_mul_(targets, 1.0 - tau)
        torch._foreach_add_(targets, params, alpha=tau)


def squashed_gaussian_sample(mean: torch.Tensor, log_std: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor]:
    """SB3's squashed diagonal Gaussian: actions ``tanh(mean + ε std)`` ``[B, d_a]`` and
    their log-densities ``[B, 1]``, with SB3's random draw and arithmetic (bit for bit)."""
    std = log_std.exp()
    gaussian = mean + torch.empty_like(mean).normal_() * std  # Normal.rsample
    action = torch.tanh(gaussian)
    log_prob = (-((gaussian - mean) ** 2) / (2 * std**2) - std.log()
                - math.log(math.sqrt(2 * math.pi))).sum(-1)
    log_prob = log_prob - torch.log(1 - action**2 + _SQUASH_EPSILON).sum(-1)
    return action, log_prob.reshape(-1, 1)


class DecomposedCritic(ContinuousCritic):
    """SB3's twin critic with ``n_rewards`` outputs per network: ``forward`` gives a tuple
    of ``n_critics`` tensors ``[B, n_rewards]``."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Box,
                 net_arch: list[int], features_extractor: BaseFeaturesExtractor,
                 features_dim: int, activation_fn: type[nn.Module] = nn.ReLU,
                 *args: Any, n_rewards: int, **kwargs: Any) -> None:
        super().__init__(observation_space, action_space, net_arch, features_extractor,
                         features_dim, activation_fn, *args, **kwargs)
        if isinstance(n_rewards, bool) or not isinstance(n_rewards, int) or n_rewards < 1:
            raise ValueError(f"n_rewards must be a positive int, got {n_rewards!r}.")
        self.n_rewards = n_rewards
        # Replace SB3's scalar heads by heads of n_rewards outputs (same layout and names).
        q_in = features_dim + get_action_dim(self.action_space)
        self.q_networks = []
        for idx in range(self.n_critics):
            q_net = nn.Sequential(*create_mlp(q_in, n_rewards, net_arch, activation_fn))
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)


class DecomposedSACPolicy(SACPolicy):
    """SB3's ``SACPolicy`` whose critics are :class:`DecomposedCritic` (``n_rewards``
    outputs each)."""

    def __init__(self, *args: Any, n_rewards: int = 1, **kwargs: Any) -> None:
        # make_critic runs inside SACPolicy.__init__, so the width must be known first.
        object.__setattr__(self, "n_rewards", n_rewards)
        super().__init__(*args, **kwargs)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None
                    ) -> DecomposedCritic:
        kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return DecomposedCritic(**kwargs, n_rewards=self.n_rewards).to(self.device)


class DecomposedSAC(SAC):
    """SB3 SAC with a fixed temperature whose critics learn one soft-Q column per reward
    column of the replay buffer's samples (module docstring). Give it
    ``policy_kwargs={"n_rewards": G}`` and a buffer whose rewards are ``[B, G]``."""

    policy_aliases = {"MlpPolicy": DecomposedSACPolicy}  # noqa: RUF012 (SB3's class dict)

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.ent_coef_optimizer is not None:
            raise ValueError("DecomposedSAC needs a fixed ent_coef (a number), not 'auto'.")
        # torch's Adam takes its per-tensor loop on CPU by default; the fused kernel does
        # Adam's arithmetic for every tensor in one call (equal to the loop up to float
        # rounding), and dispatches are what a 64x64 network's update costs. A loaded
        # optimiser state keeps the flags.
        for optimizer in (self.actor.optimizer, self.critic.optimizer):
            for group in optimizer.param_groups:
                group["foreach"], group["fused"] = False, True
        self._critic_params = list(self.critic.parameters())
        self._target_params = list(self.critic_target.parameters())
        self._actor_params = list(self.actor.parameters())

    demo_bc: float = 0.0
    """Weight of the Q-filtered demonstration loss (module docstring); 0: none."""
    demo_value_bound: bool = False
    """Bound the critics below by the demonstrated returns (module docstring)."""

    def _demo_loss(self, data, q_pi: torch.Tensor) -> torch.Tensor:
        """The module docstring's Q-filtered demonstration term on the batch's last rows
        (the buffer's demonstrated ones; ``q_pi`` ``[B, G]`` at the policy's actions)."""
        n_demo = self.replay_buffer.demo_rows(data.observations.shape[0])
        obs, demo_actions = data.observations[-n_demo:], data.actions[-n_demo:]
        with torch.no_grad():
            q_demo = torch.stack(self.critic(obs, demo_actions)).amin(0).sum(-1)  # [n]
            q_own = q_pi[-n_demo:].sum(-1)
            better = (q_demo > q_own).to(q_own.dtype)
            scale = q_pi.sum(-1).abs().mean()
        mean_actions = self.actor(obs, deterministic=True)
        gap = ((mean_actions - demo_actions) ** 2).sum(-1)
        self._demo_accept.append(better.mean())
        return self.demo_bc * scale * (better * gap).mean()

    def _action_log_prob(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SB3's ``actor.action_log_prob`` (squashed Gaussian, ``[B, d_a]`` actions and
        ``[B, 1]`` log-densities) with the same random draw and the same arithmetic, minus
        ``torch.distributions``' per-call objects and argument checks."""
        if self.use_sde:  # a state-dependent noise matrix: SB3's own path
            action, log_prob = self.actor.action_log_prob(obs)
            return action, log_prob.reshape(-1, 1)
        mean, log_std, _ = self.actor.get_action_dist_params(obs)
        return squashed_gaussian_sample(mean, log_std)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)
        self._demo_accept: list[torch.Tensor] = []
        with_demo = self.demo_bc > 0 and self.replay_buffer.demo_rows(batch_size) > 0
        with_bound = self.demo_value_bound and self.replay_buffer.demo_rows(batch_size) > 0
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        alpha = self.ent_coef_tensor
        critic_losses, actor_losses = [], []
        for step in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            if self.use_sde:
                self.actor.reset_noise()
            # Drawn before the target's next actions, in SB3's order (same random numbers).
            actions_pi, log_prob = self._action_log_prob(data.observations)
            n_rewards = data.rewards.shape[1]
            with torch.no_grad():
                next_actions, next_log_prob = self._action_log_prob(data.next_observations)
                next_q = torch.stack(self.critic_target(data.next_observations, next_actions))
                next_q = next_q.amin(0) - (alpha / n_rewards) * next_log_prob.reshape(-1, 1)
                target = data.rewards + (1 - data.dones) * self.gamma * next_q  # [B, G]
            q = self.critic(data.observations, data.actions)
            critic_loss = 0.5 * sum(((qk - target) ** 2).sum(-1).mean() for qk in q)
            if with_bound:
                returns = self.replay_buffer.sampled_demo_returns()  # [n_demo, G]
                n_demo = returns.shape[0]
                critic_loss = critic_loss + 0.5 * sum(
                    ((returns - qk[-n_demo:]).clamp(min=0) ** 2).sum(-1).mean() for qk in q)
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()

            q_pi = torch.stack(self.critic(data.observations, actions_pi)).amin(0)  # [B, G]
            actor_loss = (alpha * log_prob - q_pi.sum(-1, keepdim=True)).mean()
            if with_demo:
                actor_loss = actor_loss + self._demo_loss(data, q_pi.detach())
            self.actor.optimizer.zero_grad()
            # The actor's gradients only (SB3 also fills the critics', unused).
            actor_loss.backward(inputs=self._actor_params)
            self.actor.optimizer.step()

            if step % self.target_update_interval == 0:
                _polyak(self._critic_params, self._target_params, self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
            critic_losses.append(critic_loss.detach())
            actor_losses.append(actor_loss.detach())
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_loss", float(torch.stack(actor_losses).mean()))
        self.logger.record("train/critic_loss", float(torch.stack(critic_losses).mean()))
        if self._demo_accept:
            self.logger.record("train/demo_accept", float(torch.stack(self._demo_accept).mean()))
