"""The evaluation episodes of :meth:`SACConstrainedSolver.evaluate`: ``n`` episodes of the
joint game stepped in lock-step, only the live ones asked for.

Where the game offers a batched env (the joint env's ``vector_env(n)``,
:mod:`dicrl_torch.envs.vector`) the episodes are its slots, stepped as one array
computation; a slot whose episode has ended is stepped on (into a new episode) with a
zero action and never read. Otherwise they are ``n`` joint envs, each stepped while its
episode lasts. Both give the same transitions (the batched envs' tests), so an
evaluation's numbers do not depend on which is used.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import numpy as np

from dicrl_torch.envs.vector import JointVectorEnv
from dicrl_torch.solvers.sac.protocol import make_joint_env, protocol_attr, step_fields

__all__ = ["EpisodeSet", "episode_set"]

Step = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class EpisodeSet:
    """``n`` episodes: :meth:`reset` them with seeds, :meth:`step` the live ones."""

    def __init__(self, *, vector: JointVectorEnv | None = None,
                 envs: list[gym.Env] | None = None) -> None:
        self.vector, self.envs = vector, envs
        self.n = vector.n_envs if vector is not None else len(envs)

    def reset(self, seeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Episode ``k`` seeded by ``seeds[k]``: observations ``[n, d_o]`` and joint
        states ``[n, N, d_s]`` float64."""
        if self.vector is not None:
            return self.vector.reset([int(s) for s in seeds])
        starts = [env.reset(seed=int(s)) for env, s in zip(self.envs, seeds, strict=True)]
        return (np.stack([o for o, _ in starts]),
                np.stack([np.array(info["state"], dtype=np.float64) for _, info in starts]))

    def step(self, idx: np.ndarray, actions: np.ndarray) -> Step:
        """Step episodes ``idx`` with their ``actions`` ``[len(idx), d_a]``: their
        observations, joint states, ``terminated``, ``truncated``, ``reached`` and
        ``violated``, rows in ``idx``'s order."""
        if self.vector is not None:
            full = np.zeros((self.n, *np.shape(actions)[1:]), dtype=np.float64)
            full[idx] = actions
            s = self.vector.step(full)
            return (s.final_obs[idx], s.states[idx], s.terminated[idx], s.truncated[idx],
                    s.reached[idx], s.violated[idx])
        rows = []
        for j, i in enumerate(idx):
            o, _, term, trunc, info = self.envs[i].step(actions[j])
            state, reached, violated = step_fields(info)
            rows.append((o, state, bool(term), bool(trunc) and not term, reached, violated))
        return tuple(np.stack(column) for column in zip(*rows, strict=True))

    def close(self) -> None:
        if self.vector is not None:
            self.vector.close()
        for env in self.envs or []:
            env.close()


def episode_set(env_factory: Callable[..., gym.Env], constrained: bool, n: int,
                batched: bool) -> EpisodeSet:
    """``n`` episodes of ``env_factory(constrained=constrained)``'s game: the game's own
    vector env when ``batched`` and it has one, else ``n`` joint envs."""
    probe = make_joint_env(env_factory, constrained=constrained)
    vector = None
    if batched:
        factory = protocol_attr(probe, "vector_env")
        vector = factory(int(n)) if callable(factory) else None
    if vector is not None:
        probe.close()
        return EpisodeSet(vector=vector)
    return EpisodeSet(envs=[probe] + [make_joint_env(env_factory, constrained=constrained)
                                      for _ in range(int(n) - 1)])
