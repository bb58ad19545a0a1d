"""Any joint env as a :class:`~dicrl_torch.envs.vector.JointVectorEnv`: ``n_envs`` copies
stepped one after the other (:class:`EnvList`, the reference every batched game
reproduces), and :func:`vector_env_of`, which prefers the game's own batched env."""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from dicrl_torch.envs.vector import JointVectorEnv, VectorStep
from dicrl_torch.solvers.sac.state import env_state_dict, load_env_state_dict

__all__ = ["EnvList", "vector_env_of"]


class EnvList(JointVectorEnv):
    """Any joint env, ``n_envs`` copies stepped one after the other (the reference
    behaviour every batched game reproduces).

    Args:
        make_env: builds one joint env (e.g. ``lambda: env_factory(constrained=False)``).
        n_envs: slots.
    """

    def __init__(self, make_env: Callable[[], gym.Env], n_envs: int) -> None:
        self.envs = [make_env() for _ in range(int(n_envs))]
        probe = self.envs[0]
        self.n_envs = len(self.envs)
        self.n_agents = int(probe.get_wrapper_attr("n_agents"))
        self.state_shape = tuple(int(d) for d in probe.get_wrapper_attr("state_shape"))
        self.observation_space = probe.observation_space
        self.action_space = probe.action_space

    def reset(self, seeds: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        starts = [env.reset(seed=int(s)) for env, s in zip(self.envs, seeds, strict=True)]
        return (np.stack([np.asarray(o, dtype=np.float32) for o, _ in starts]),
                np.stack([np.asarray(info["state"], dtype=np.float64) for _, info in starts]))

    def step(self, actions: np.ndarray) -> VectorStep:
        n = self.n_envs
        obs = np.zeros((n, *self.observation_space.shape), dtype=np.float32)
        final = np.zeros_like(obs)
        states = np.zeros((n, *self.state_shape))
        terminated, truncated = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        reached = np.zeros((n, self.n_agents), dtype=bool)
        violated = np.zeros((n, self.n_agents), dtype=bool)
        for k, env in enumerate(self.envs):
            o, _, term, trunc, info = env.step(actions[k])
            final[k] = obs[k] = o
            states[k] = _field(info, "state")
            reached[k], violated[k] = _field(info, "reached"), _field(info, "violated")
            terminated[k], truncated[k] = bool(term), bool(trunc) and not term
            if term or trunc:
                obs[k] = env.reset()[0]
        return VectorStep(obs=obs, final_obs=final, states=states, terminated=terminated,
                          truncated=truncated, reached=reached, violated=violated)

    def set_rng(self, slot: int, rng: np.random.Generator) -> None:
        set_rng = _protocol_attr(self.envs[slot], "set_rng")
        if callable(set_rng):
            set_rng(rng)

    def state_dict(self) -> dict[str, Any]:
        return {"n_envs": self.n_envs, "envs": [env_state_dict(env) for env in self.envs]}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if int(sd["n_envs"]) != self.n_envs or len(sd["envs"]) != self.n_envs:
            raise ValueError(f"training envs: the state holds {sd['n_envs']}, this solver "
                             f"{self.n_envs} (n_envs); load it into a solver built with the "
                             f"same arguments.")
        trial = copy.deepcopy(self.envs)  # all or nothing
        for k, (env, state) in enumerate(zip(trial, sd["envs"], strict=True)):
            try:
                load_env_state_dict(env, state)
            except ValueError as e:
                raise ValueError(f"training env {k}: {e}") from None
        self.envs = trial

    def close(self) -> None:
        for env in self.envs:
            env.close()


def _protocol_attr(env: gym.Env, name: str) -> Any:
    try:
        return env.get_wrapper_attr(name)
    except AttributeError:
        return None


def _field(info: dict[str, Any], key: str) -> Any:
    try:
        return info[key]
    except KeyError:
        raise ValueError(f"The env's step info has no {key!r}: every step must give 'state' "
                         f"[N, d_s] and the per-agent [N] bools 'reached' and 'violated' "
                         f"(False where the game has no such notion); see the joint-env "
                         f"protocol of dicrl_torch.solvers.sac.") from None


def vector_env_of(make_env: Callable[[], gym.Env], n_envs: int,
                  batched: bool = True) -> JointVectorEnv:
    """The game's own batched :class:`JointVectorEnv` when its joint env offers one
    (``vector_env(n_envs)`` returning not None) and ``batched``, else an
    :class:`EnvList` of ``n_envs`` joint envs."""
    if batched:
        probe = make_env()
        try:
            factory = _protocol_attr(probe, "vector_env")
            vec = factory(int(n_envs)) if callable(factory) else None
        finally:
            probe.close()
        if vec is not None:
            return vec
    return EnvList(make_env, n_envs)
