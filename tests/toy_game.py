"""A game of a user's own, registered through its own config group (tests/toy_configs/)
and task builder, without a change to the library's runs/ or experiments/: two agents
crossing the unit square to the right edge, with a forbidden square in the middle.

``toy_task`` is what ``env.task._target_`` names in tests/toy_configs/env/toy.yaml."""

from __future__ import annotations

import functools

import numpy as np
import torch
from gymnasium import spaces
from hydra.utils import instantiate
from omegaconf import OmegaConf
from pettingzoo import ParallelEnv

from dicrl_torch.demos.continuous import record_demonstrations
from dicrl_torch.envs.joint import JointAgentEnv
from dicrl_torch.features.continuous import ContinuousFeatureBasis, PositionCellBasis
from dicrl_torch.runs.continuous import SACTask

STARTS = np.array([[0.1, 0.25], [0.1, 0.75]])
GOAL_X, BLOCK, STEP = 0.9, (0.4, 0.6), 0.1


class Crossing(ParallelEnv):
    """Agent ``i`` starts at ``STARTS[i]`` and moves by ``STEP * action`` (``[-1, 1]^2``)
    per step; it has reached its goal once ``x >= GOAL_X``. Entering the middle square
    ``BLOCK^2`` violates the constraint; in the true game (``constrained``) a violator
    freezes. State: ``[N, 2]`` positions."""

    metadata = {"name": "crossing_v0"}

    def __init__(self, constrained: bool = False, max_steps: int = 12) -> None:
        self.constrained, self.max_steps = constrained, max_steps
        self.possible_agents = ["agent_0", "agent_1"]
        self.agents: list[str] = []
        self._observation_space = spaces.Box(0.0, 1.0, (2,), np.float32)
        self._action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.state_space = spaces.Box(0.0, 1.0, (2, 2), np.float32)

    def observation_space(self, agent):
        return self._observation_space

    def action_space(self, agent):
        return self._action_space

    def state(self) -> np.ndarray:
        return self.pos.copy()

    def _obs(self) -> dict:
        return {a: self.pos[i].astype(np.float32) for i, a in enumerate(self.possible_agents)}

    def reset(self, seed=None, options=None):
        self.pos, self.t = STARTS.copy(), 0
        self.frozen = np.zeros(2, bool)
        self.agents = list(self.possible_agents)
        return self._obs(), {a: {} for a in self.agents}

    def step(self, actions):
        for i, a in enumerate(self.possible_agents):
            if a in actions and not self.frozen[i]:
                move = np.clip(np.asarray(actions[a], np.float64), -1.0, 1.0)
                self.pos[i] = np.clip(self.pos[i] + STEP * move, 0.0, 1.0)
        self.t += 1
        inside = ((self.pos > BLOCK[0]) & (self.pos < BLOCK[1])).all(axis=1)
        if self.constrained:
            self.frozen |= inside
        reached = self.pos[:, 0] >= GOAL_X
        infos = {a: {"violated": bool(inside[i]), "reached": bool(reached[i])}
                 for i, a in enumerate(self.possible_agents)}
        done = self.t >= self.max_steps
        obs = self._obs()
        self.agents = [] if done else self.agents
        return (obs, {a: float(reached[i]) for i, a in enumerate(self.possible_agents)},
                {a: False for a in self.possible_agents},
                {a: done for a in self.possible_agents}, infos)


class GoalCloseness(ContinuousFeatureBasis):
    """Reward features ``[..., N, 2] -> [..., N]``: each agent's ``x``, its progress."""

    def __init__(self) -> None:
        super().__init__()
        self.names, self.n_agents, self.max_value = ["agent0/x", "agent1/x"], 2, 1.0

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        return states[..., :, 0].clamp(0.0, 1.0)


def straight_experts(observations: dict, env) -> dict:
    """Straight to the right edge: the starts' rows pass beside the block."""
    return {a: np.array([1.0, 0.0], np.float32) for a in env.agents}


def make_env(constrained: bool = False, **arena) -> JointAgentEnv:
    return JointAgentEnv(Crossing(constrained=constrained, **arena), observation="state")


def cell_costs(n_per_axis: int = 5) -> PositionCellBasis:
    return PositionCellBasis(n_agents=2, bounds=[(0.0, 1.0)] * 2, n_per_axis=n_per_axis,
                             proximity_radius=0.2)


def toy_task(cfg, rank: int | None = None) -> SACTask:
    """The task builder ``env.task._target_`` names: ``(cfg, rank) -> task``."""
    from common import sac_task_settings  # the shipped games' SAC settings, as a user would

    arena = OmegaConf.to_container(cfg.env.arena)
    reward, cost = instantiate(cfg.features.reward), instantiate(cfg.features.cost)
    solver = instantiate(cfg.solver.solver, reward_basis=reward, cost_basis=cost,
                         seed=cfg.seed, env_factory=functools.partial(make_env, **arena))
    demos = record_demonstrations(Crossing(constrained=True, **arena), straight_experts,
                                  sum(cfg.split), seed=cfg.seed)
    return SACTask(solver=solver, demos=demos, **sac_task_settings(cfg))
