"""One SAC gradient update of an ensemble of learners, with the solver's extra terms.

The arithmetic is :class:`~dicrl_torch.solvers.sac.decomposed.DecomposedSAC`'s (SB3's
SAC with a fixed temperature, soft-Q columns per reward column, the Q-filtered
demonstration loss and the demonstrated-return bound; the formulas are in that module's
docstring), in SB3's order: the policy's actions at ``s`` and ``s'`` are drawn, the
critics step on the soft Bellman targets of the target critics, then the actor steps
against the updated critics, then the targets move by Polyak averaging. What differs is
how it is computed: the networks of :mod:`~dicrl_torch.solvers.sac.networks` (one
``baddbmm`` per layer for every learner and both critics), one forward pass of the actor
for ``s`` and ``s'`` together where no gradient is needed for ``s'``, and Adam as one
fused call on each network's tensors without ``torch.optim``'s per-step bookkeeping.
``tests/test_sac_update.py`` checks an update against ``DecomposedSAC.train`` on the
same weights, batch and noise.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from dicrl_torch.solvers.sac.networks import EnsembleActor, EnsembleCritic, squashed_sample

__all__ = ["Batch", "EnsembleSAC", "FusedAdam"]


@dataclass
class Batch:
    """``E`` learners' batches of ``B`` transitions, the last ``n_demo`` rows of each
    drawn from its demonstrations.

    Attributes:
        obs, next_obs: ``[E, B, d_o]`` float32 (as the networks read them).
        actions: ``[E, B, d_a]`` float32 in ``[-1, 1]``.
        rewards: ``[E, B, G]`` float32.
        dones: ``[E, B, 1]`` float32, 1 where ``s'`` is terminal (no bootstrap).
        n_demo: demonstrated rows at the end of each batch.
        demo_returns: ``[E, n_demo, G]`` float32 discounted returns of those rows (for
            the value bound), or None.
    """

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    dones: torch.Tensor
    n_demo: int = 0
    demo_returns: torch.Tensor | None = None

    @staticmethod
    def stack(batches: Sequence[Batch], device: torch.device) -> Batch:
        """Learners' batches (each ``E = 1``, the same ``B`` and ``n_demo``) as one, on
        ``device``."""
        def cat(name: str) -> torch.Tensor:
            return torch.cat([getattr(b, name) for b in batches]).to(device)

        first = batches[0]
        if len(batches) == 1 and first.obs.device == device:
            return first
        return Batch(obs=cat("obs"), actions=cat("actions"), rewards=cat("rewards"),
                     next_obs=cat("next_obs"), dones=cat("dones"), n_demo=first.n_demo,
                     demo_returns=None if first.demo_returns is None else cat("demo_returns"))


class FusedAdam:
    """Adam (torch's defaults but ``lr``) on a list of tensors as one fused call:
    ``torch.optim.Adam(params, lr, fused=True)``'s arithmetic, bit for bit, without its
    per-step Python (a third of an update of 64-unit networks)."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float) -> None:
        self.params = list(params)
        self.lr = float(lr)
        self.exp_avgs = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sqs = [torch.zeros_like(p) for p in self.params]
        self.steps = [torch.zeros((), dtype=torch.float32) for _ in self.params]

    def step(self) -> None:
        """Apply the gradients in ``.grad`` and clear them."""
        grads = [p.grad for p in self.params]
        torch._foreach_add_(self.steps, 1)
        torch._fused_adam_(self.params, grads, self.exp_avgs, self.exp_avg_sqs, [],
                           self.steps, amsgrad=False, lr=self.lr, beta1=0.9, beta2=0.999,
                           weight_decay=0.0, eps=1e-8, maximize=False)
        for p in self.params:
            p.grad = None

    def state_dict(self) -> dict[str, Any]:
        return {"lr": self.lr, "exp_avgs": [t.clone() for t in self.exp_avgs],
                "exp_avg_sqs": [t.clone() for t in self.exp_avg_sqs],
                "steps": [t.clone() for t in self.steps]}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        with torch.no_grad():
            for mine, theirs in ((self.exp_avgs, sd["exp_avgs"]),
                                 (self.exp_avg_sqs, sd["exp_avg_sqs"]),
                                 (self.steps, sd["steps"])):
                for m, t in zip(mine, theirs, strict=True):
                    m.copy_(t)


class EnsembleSAC:
    """Networks, targets and optimisers of ``E`` learners' SAC, and their update.

    Args:
        obs_dim, action_dim: observation and (joint) action sizes.
        hidden: hidden layer widths of actor and critics.
        n_rewards: ``G`` soft-Q columns per critic.
        generators: one ``torch.Generator`` per learner, for its initial weights.
        learning_rate: Adam's, both networks.
        gamma: discount.
        ent_coef: the fixed temperature ``α``.
        tau: Polyak rate of the target critics.
        demo_bc: weight of the Q-filtered demonstration loss (0: none).
        demo_value_bound: bound the critics below by the demonstrated returns.
    """

    def __init__(self, *, obs_dim: int, action_dim: int, hidden: Sequence[int],
                 n_rewards: int, generators: Sequence[torch.Generator],
                 learning_rate: float, gamma: float, ent_coef: float, tau: float,
                 demo_bc: float = 0.0, demo_value_bound: bool = False) -> None:
        self.actor = EnsembleActor(obs_dim, action_dim, hidden, generators)
        self.critic = EnsembleCritic(obs_dim, action_dim, hidden, n_rewards, generators)
        self.target = [p.detach().clone() for p in self.critic.params]
        self.actor_optimizer = FusedAdam(self.actor.params, learning_rate)
        self.critic_optimizer = FusedAdam(self.critic.params, learning_rate)
        self.n_learners = len(generators)
        self.action_dim, self.n_rewards = int(action_dim), int(n_rewards)
        self.gamma, self.alpha, self.tau = float(gamma), float(ent_coef), float(tau)
        self.demo_bc, self.demo_value_bound = float(demo_bc), bool(demo_value_bound)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """Actions ``[E, n, d_a]`` in ``[-1, 1]`` at ``obs`` ``[E, n, d_o]``: sampled with
        ``noise`` (standard normal ``[E, n, d_a]``), or ``tanh`` of the mean (None)."""
        with torch.no_grad():
            mean, log_std = self.actor.dist_params(obs)
            return torch.tanh(mean if noise is None else mean + noise * log_std.exp())

    def update(self, batch: Batch, noise: torch.Tensor) -> None:
        """One gradient step of every learner on its batch; ``noise`` ``[E, 2, B, d_a]``
        standard normal draws of the policy's actions at ``s`` (``[:, 0]``) and at ``s'``
        (``[:, 1]``)."""
        obs, b = batch.obs, batch.obs.shape[1]
        mean, log_std = self.actor.dist_params(obs)
        actions_pi, log_prob = squashed_sample(mean, log_std, noise[:, 0])
        with torch.no_grad():
            next_actions, next_log_prob = squashed_sample(
                *self.actor.dist_params(batch.next_obs), noise[:, 1])
            next_q = self.critic.forward_with(self.target, batch.next_obs, next_actions)
            next_q = next_q.amin(1) - (self.alpha / self.n_rewards) * next_log_prob
            target = batch.rewards + (1 - batch.dones) * self.gamma * next_q  # [E, B, G]
        q = self.critic.forward_with(self.critic.params, obs, batch.actions)  # [E, 2, B, G]
        # Each learner's loss is its own (its slice); their sum leaves them independent.
        critic_loss = 0.5 * ((q - target.unsqueeze(1)) ** 2).sum(-1).mean(-1).sum()
        n_demo = batch.n_demo
        if self.demo_value_bound and n_demo > 0:
            gap = (batch.demo_returns.unsqueeze(1) - q[:, :, -n_demo:]).clamp(min=0)
            critic_loss = critic_loss + 0.5 * (gap ** 2).sum(-1).mean(-1).sum()
        critic_loss.backward()
        self.critic_optimizer.step()

        with_demo = self.demo_bc > 0 and n_demo > 0
        # The actor's loss differentiates through the critics to the actions only.
        frozen = [p.detach() for p in self.critic.params]
        if with_demo:  # the critics at the demonstrated actions too, in the same pass
            q_all = self.critic.forward_with(
                frozen, torch.cat([obs, obs[:, -n_demo:]], 1),
                torch.cat([actions_pi, batch.actions[:, -n_demo:]], 1)).amin(1)
            q_pi, q_demo = q_all[:, :b], q_all[:, b:].detach().sum(-1)  # [E, B, G], [E, n]
        else:
            q_pi = self.critic.forward_with(frozen, obs, actions_pi).amin(1)
        actor_loss = (self.alpha * log_prob - q_pi.sum(-1, keepdim=True)).mean((1, 2)).sum()
        if with_demo:
            actor_loss = actor_loss + self._demo_loss(mean[:, b - n_demo:], q_demo,
                                                      q_pi.detach(), batch)
        actor_loss.backward()
        self.actor_optimizer.step()
        with torch.no_grad():
            torch._foreach_mul_(self.target, 1.0 - self.tau)
            torch._foreach_add_(self.target, self.critic.params, alpha=self.tau)

    def _demo_loss(self, demo_mean: torch.Tensor, q_demo: torch.Tensor, q_pi: torch.Tensor,
                   batch: Batch) -> torch.Tensor:
        """The Q-filtered demonstration term (summed over learners): ``demo_mean``
        ``[E, n, d_a]`` the actor's pre-squash means at the demonstrated rows, ``q_demo``
        ``[E, n]`` the critics at the demonstrated actions, ``q_pi`` ``[E, B, G]``
        (detached) at the policy's."""
        n_demo = batch.n_demo
        better = (q_demo > q_pi[:, -n_demo:].sum(-1)).to(q_pi.dtype)  # [E, n]
        scale = q_pi.sum(-1).abs().mean(-1, keepdim=True)  # [E, 1]
        gap = ((torch.tanh(demo_mean) - batch.actions[:, -n_demo:]) ** 2).sum(-1)
        return (self.demo_bc * scale * (better * gap).mean(-1, keepdim=True)).sum()

    # ---- ensembles of several solvers' learners ----------------------------------
    @classmethod
    def stacked(cls, members: Sequence[EnsembleSAC]) -> EnsembleSAC:
        """One ensemble of every learner of ``members`` (in order): copies of their
        networks, targets and Adam moments. They must have taken as many updates (Adam's
        step count is one per tensor) and share their settings."""
        first = members[0]
        if len({tuple(float(t) for t in m.actor_optimizer.steps) for m in members}) > 1:
            raise ValueError("Only learners that took as many updates can be stacked.")
        new = copy.copy(first)
        new.actor, new.critic = copy.deepcopy(first.actor), copy.deepcopy(first.critic)
        with torch.no_grad():
            for net, name in ((new.actor, "actor"), (new.critic, "critic")):
                for k, p in enumerate(net.params):
                    p.data = torch.cat([getattr(m, name).params[k].detach() for m in members])
                net.n_learners = sum(getattr(m, name).n_learners for m in members)
            new.target = [torch.cat([m.target[k] for m in members])
                          for k in range(len(first.target))]
        new.n_learners = new.actor.n_learners
        for name, net in (("actor_optimizer", new.actor), ("critic_optimizer", new.critic)):
            opts = [getattr(m, name) for m in members]
            opt = FusedAdam(net.params, opts[0].lr)
            opt.exp_avgs = [torch.cat([o.exp_avgs[k] for o in opts])
                            for k in range(len(opt.params))]
            opt.exp_avg_sqs = [torch.cat([o.exp_avg_sqs[k] for o in opts])
                               for k in range(len(opt.params))]
            opt.steps = [t.clone() for t in opts[0].steps]
            setattr(new, name, opt)
        return new

    def unstack_into(self, members: Sequence[EnsembleSAC]) -> None:
        """Write this :meth:`stacked` ensemble's learners back into ``members``."""
        with torch.no_grad():
            for name in ("actor", "critic"):
                start = 0
                for m in members:
                    size = getattr(m, name).params[0].shape[0]
                    for p, q in zip(getattr(m, name).params, getattr(self, name).params,
                                    strict=True):
                        p.copy_(q[start:start + size])
                    opt, mine = getattr(m, f"{name}_optimizer"), getattr(self, f"{name}_optimizer")
                    for lists, ours in ((opt.exp_avgs, mine.exp_avgs),
                                        (opt.exp_avg_sqs, mine.exp_avg_sqs)):
                        for t, u in zip(lists, ours, strict=True):
                            t.copy_(u[start:start + size])
                    for t, u in zip(opt.steps, mine.steps, strict=True):
                        t.copy_(u)
                    if name == "critic":
                        for t, u in zip(m.target, self.target, strict=True):
                            t.copy_(u[start:start + size])
                    start += size

    # ---- state --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Networks, targets and both optimisers (tensors and plain values)."""
        return {"actor": {k: v.detach().clone() for k, v in self.actor.state_dict().items()},
                "critic": {k: v.detach().clone()
                           for k, v in self.critic.state_dict().items()},
                "target": [t.clone() for t in self.target],
                "actor_optimizer": self.actor_optimizer.state_dict(),
                "critic_optimizer": self.critic_optimizer.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.actor.load_state_dict(sd["actor"])
        self.critic.load_state_dict(sd["critic"])
        with torch.no_grad():
            for t, s in zip(self.target, sd["target"], strict=True):
                t.copy_(s)
        self.actor_optimizer.load_state_dict(sd["actor_optimizer"])
        self.critic_optimizer.load_state_dict(sd["critic_optimizer"])

    def policy_state(self) -> dict[str, torch.Tensor]:
        """Actor, critics and targets (not the optimisers): what a scored chunk keeps."""
        sd = self.state_dict()
        return {**{f"actor.{k}": v for k, v in sd["actor"].items()},
                **{f"critic.{k}": v for k, v in sd["critic"].items()},
                **{f"target.{k}": v for k, v in enumerate(sd["target"])}}

    def load_policy_state(self, state: dict[str, torch.Tensor]) -> None:
        with torch.no_grad():
            for k, v in self.actor.state_dict().items():
                v.copy_(state[f"actor.{k}"])
            for k, v in self.critic.state_dict().items():
                v.copy_(state[f"critic.{k}"])
            for k, t in enumerate(self.target):
                t.copy_(state[f"target.{k}"])
