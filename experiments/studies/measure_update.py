"""Time one SAC gradient update of the drone solver's shapes, several ways
(docs/performance.md, "The SAC solver").

    .venv/bin/python experiments/studies/measure_update.py           # separate, ensemble
    .venv/bin/python experiments/studies/measure_update.py \\
        --kinds separate ensemble compile separate
    .venv/bin/python experiments/studies/measure_update.py \\
        --kinds lean lean_compile lean lean_compile --columns 3

The update is ``DecomposedSAC.train``'s arithmetic as a plain loop, without SB3 or a replay
buffer: batch 256, a 64x64 squashed-Gaussian actor, two 64x64 critics of ``--columns`` soft-Q
columns (one per drone), fused Adam, Polyak targets (on all tensors at once, as
``DecomposedSAC.train`` does; the same bits as SB3's ``polyak_update``), ``--threads`` torch
threads (1). The kinds:

- ``separate``: the two critics as two ``nn.Sequential`` (as SB3's loop builds them);
- ``ensemble``: the two critics as one network whose layers are ``baddbmm`` over a leading
  axis of 2 (one kernel per layer for both);
- ``compile``: ``separate`` with the three loss computations through ``torch.compile``
  (the first updates include the compilation, reported apart);
- ``lean``: the shipped update, :class:`~dicrl_torch.solvers.sac.update.EnsembleSAC` of one
  learner (its critics' ``G`` columns are ``--columns``);
- ``lean_compile``: ``lean`` with the actor's and the critics' forward passes through
  ``torch.compile`` (AOTAutograd compiles their backward too; Adam and the Polyak step stay
  eager: ``torch._fused_adam_`` cannot be traced).

Prints one JSON line per kind, in the order given (repeat a kind to alternate them): the
median over ``--repeat`` runs of ``--updates`` updates, in ms per update. The inputs are
random (the time of an update does not depend on its values).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch
from torch import nn

from dicrl_torch.solvers.sac.decomposed import squashed_gaussian_sample
from dicrl_torch.solvers.sac.update import Batch, EnsembleSAC

BATCH, OBS, ACT, HIDDEN = 256, 8, 4, 64


def polyak(params: list[torch.Tensor], targets: list[torch.Tensor], tau: float) -> None:
    """``target ← (1 − τ) target + τ param`` on all tensors at once: SB3's ``polyak_update``
    (the same two operations, so the same bits) in two kernels, as ``DecomposedSAC`` does."""
    with torch.no_grad():
        torch._foreach_mul_(targets, 1.0 - tau)
        torch._foreach_add_(targets, params, alpha=tau)


def _mlp(n_in: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN),
                         nn.ReLU(), nn.Linear(HIDDEN, n_out))


class Actor(nn.Module):
    """SB3's SAC actor: a shared 64x64 body, mean and log-std heads."""

    def __init__(self) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(OBS, HIDDEN), nn.ReLU(),
                                  nn.Linear(HIDDEN, HIDDEN), nn.ReLU())
        self.mean, self.log_std = nn.Linear(HIDDEN, ACT), nn.Linear(HIDDEN, ACT)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Squashed-Gaussian actions ``[B, ACT]`` and log-densities ``[B, 1]``."""
        h = self.body(obs)
        return squashed_gaussian_sample(self.mean(h), self.log_std(h).clamp(-20, 2))


class SeparateCritics(nn.Module):
    """Two critics as two networks: ``[2, B, columns]``."""

    def __init__(self, columns: int) -> None:
        super().__init__()
        self.nets = nn.ModuleList([_mlp(OBS + ACT, columns) for _ in range(2)])

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, act], 1)
        return torch.stack([net(x) for net in self.nets])


class EnsembleCritics(nn.Module):
    """Two critics as one batched network: ``[2, B, columns]``."""

    def __init__(self, columns: int) -> None:
        super().__init__()
        dims = [OBS + ACT, HIDDEN, HIDDEN, columns]
        self.weights = nn.ParameterList([nn.Parameter(torch.randn(2, i, o) / math.sqrt(i))
                                         for i, o in zip(dims[:-1], dims[1:], strict=True)])
        self.biases = nn.ParameterList([nn.Parameter(torch.zeros(2, 1, o)) for o in dims[1:]])

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, act], 1).expand(2, -1, -1)
        for k, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = torch.baddbmm(b, x, w)
            if k < len(self.weights) - 1:
                x = torch.relu(x)
        return x


def make_lean_update(compiled: bool, columns: int, alpha: float = 0.1, gamma: float = 0.99,
                     tau: float = 0.02):
    """The shipped ensemble update of one learner, with :func:`make_update`'s signature."""
    sac = EnsembleSAC(obs_dim=OBS, action_dim=ACT, hidden=(HIDDEN, HIDDEN), n_rewards=columns,
                      generators=[torch.Generator().manual_seed(0)], learning_rate=1e-3,
                      gamma=gamma, ent_coef=alpha, tau=tau)
    if compiled:
        sac.critic.forward_with = torch.compile(sac.critic.forward_with)
        sac.actor.dist_params = torch.compile(sac.actor.dist_params)

    def update(obs, act, rewards, next_obs, dones):
        sac.update(Batch(obs=obs[None], actions=act[None], rewards=rewards[None],
                         next_obs=next_obs[None], dones=dones[None]),
                   torch.randn(1, 2, obs.shape[0], ACT))

    update.actor, update.critic = sac.actor, sac.critic
    return update


def make_update(kind: str, columns: int, alpha: float = 0.1, gamma: float = 0.99,
                tau: float = 0.02):
    """One SAC update ``(obs, act, rewards [B, columns], next_obs, dones) -> None``."""
    if kind in ("lean", "lean_compile"):
        return make_lean_update(kind == "lean_compile", columns, alpha, gamma, tau)
    actor = Actor()
    critic_cls = EnsembleCritics if kind == "ensemble" else SeparateCritics
    critic, target = critic_cls(columns), critic_cls(columns)
    target.load_state_dict(critic.state_dict())
    actor_opt = torch.optim.Adam(actor.parameters(), 1e-3, fused=True)
    critic_opt = torch.optim.Adam(critic.parameters(), 1e-3, fused=True)
    params, targets = list(critic.parameters()), list(target.parameters())
    actor_params = list(actor.parameters())

    def policy(obs):
        return actor.sample(obs)

    def critic_loss(obs, act, rewards, next_obs, dones):
        with torch.no_grad():
            next_act, next_log_prob = actor.sample(next_obs)
            next_q = target(next_obs, next_act).amin(0) - (alpha / columns) * next_log_prob
            y = rewards + (1 - dones) * gamma * next_q
        return 0.5 * ((critic(obs, act) - y) ** 2).sum(-1).mean(-1).sum()

    def actor_loss(obs, act_pi, log_prob):
        return (alpha * log_prob - critic(obs, act_pi).amin(0).sum(-1, keepdim=True)).mean()

    if kind == "compile":
        policy, critic_loss, actor_loss = (torch.compile(f) for f in
                                           (policy, critic_loss, actor_loss))

    def update(obs, act, rewards, next_obs, dones):
        act_pi, log_prob = policy(obs)
        loss = critic_loss(obs, act, rewards, next_obs, dones)
        critic_opt.zero_grad()
        loss.backward()
        critic_opt.step()
        loss = actor_loss(obs, act_pi, log_prob)
        actor_opt.zero_grad()
        loss.backward(inputs=actor_params)
        actor_opt.step()
        polyak(params, targets, tau)

    update.actor, update.critic = actor, critic  # for a test that an update trains them
    return update


def batch(columns: int) -> tuple[torch.Tensor, ...]:
    return (torch.randn(BATCH, OBS), torch.rand(BATCH, ACT) * 2 - 1,
            torch.randn(BATCH, columns), torch.randn(BATCH, OBS), torch.zeros(BATCH, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", nargs="+", default=["separate", "ensemble"],
                        choices=["separate", "ensemble", "compile", "lean", "lean_compile"])
    parser.add_argument("--updates", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--columns", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    for kind in args.kinds:
        update = make_update(kind, args.columns)
        t0 = time.perf_counter()
        for _ in range(5):  # first calls: allocations, and compile's compilation
            update(*batch(args.columns))
        first = time.perf_counter() - t0
        data = [batch(args.columns) for _ in range(args.updates)]
        runs = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            for x in data:
                update(*x)
            runs.append((time.perf_counter() - t0) / args.updates * 1e3)
        print(json.dumps({"kind": kind, "threads": args.threads,
                          "ms_per_update": round(statistics.median(runs), 2),
                          "runs": [round(r, 2) for r in runs],
                          "first_5_updates_s": round(first, 2)}), flush=True)


if __name__ == "__main__":
    main()
