"""What a SAC engine is built from: :class:`EngineSettings`, checked and assembled once
by :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` and handed to whichever engine
it runs (:class:`~dicrl_torch.solvers.sac.lean.LeanEngine` or
:class:`~dicrl_torch.solvers.sac.sb3_engine.SB3Engine`), so that the two loops share one
list of settings instead of repeating it."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from dicrl_torch.solvers.sac.protocol import JointEnvSpec

__all__ = ["EngineSettings"]


@dataclass(frozen=True)
class EngineSettings:
    """The settings both engines take, as :class:`SACConstrainedSolver` holds them.

    Attributes:
        env_factory: the solver's (``env_factory(constrained=False)`` is trained in).
        spec: the joint env's :class:`~dicrl_torch.solvers.sac.protocol.JointEnvSpec`.
        reward_basis, cost_basis: the feature modules the replay rows are labelled with.
        seed: the engine's streams are drawn from it.
        device: where the networks live.
        n_envs, gamma, ent_coef, absorbing, learning_rate, buffer_size, batch_size,
            learning_starts, tau, train_freq, gradient_steps, net_arch, feature_dtype,
            scale_observations, per_agent_critics, split_cost_critic, demo_bc,
            demo_value_bound: as :class:`SACConstrainedSolver`'s arguments.
    """

    env_factory: Callable[..., Any]
    spec: JointEnvSpec
    reward_basis: torch.nn.Module
    cost_basis: torch.nn.Module
    seed: int
    n_envs: int
    device: torch.device
    gamma: float
    ent_coef: float
    absorbing: bool
    learning_rate: float
    buffer_size: int
    batch_size: int
    learning_starts: int
    tau: float
    train_freq: int
    gradient_steps: int
    net_arch: Sequence[int]
    feature_dtype: Any
    scale_observations: bool
    per_agent_critics: bool
    split_cost_critic: bool
    demo_bc: float
    demo_value_bound: bool

    @property
    def n_rewards(self) -> int:
        """Soft-Q columns per critic: one per agent with ``per_agent_critics``, twice
        with ``split_cost_critic`` (the reward and the cost part apart)."""
        return ((self.spec.n_agents if self.per_agent_critics else 1)
                * (2 if self.split_cost_critic else 1))
