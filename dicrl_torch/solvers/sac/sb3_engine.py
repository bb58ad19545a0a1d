"""The solver's SAC through stable-baselines3 (``engine="sb3"``): the reference loop.

SB3's ``SAC.learn`` on a ``DummyVecEnv`` of ``Monitor``-wrapped joint envs, with the
solver's :class:`~dicrl_torch.solvers.sac.buffer.FeatureReplayBuffer` and, for decomposed
critics or demonstration terms, :class:`~dicrl_torch.solvers.sac.decomposed.DecomposedSAC`.
SB3 draws from the global random streams; every call runs on the engine's private copies
of them (restored for the caller after). The default engine is the lean loop
(:mod:`~dicrl_torch.solvers.sac.lean`), which does the same with fewer layers; this one
is what it is measured and tested against.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv

from dicrl_torch.solvers.sac.buffer import FeatureReplayBuffer
from dicrl_torch.solvers.sac.decomposed import DecomposedSAC
from dicrl_torch.solvers.sac.engine_settings import EngineSettings
from dicrl_torch.solvers.sac.features import BoxScaler
from dicrl_torch.solvers.sac.protocol import protocol_attr
from dicrl_torch.solvers.sac.randomness import (
    capture_global_rng,
    global_rng_from_state_dict,
    global_rng_state_dict,
    restore_global_rng,
    seed_global_rng,
)
from dicrl_torch.solvers.sac.state import (
    check_model_state,
    check_vec_env_state,
    load_model_state_dict,
    load_vec_env_state_dict,
    model_state_dict,
    vec_env_state_dict,
)

__all__ = ["SB3Engine"]


class SB3Engine:
    """SAC through SB3 (module docstring).

    Args:
        s: the settings (:class:`EngineSettings`).
        sac_kwargs: further keyword arguments of ``stable_baselines3.SAC``.
    """

    name = "sb3"

    def __init__(self, s: EngineSettings, *,
                 sac_kwargs: dict[str, Any] | None = None) -> None:
        self.seed, self.device, self.n_envs = int(s.seed), s.device, int(s.n_envs)
        self._rng_state: tuple[Any, ...] | None = None
        kwargs = dict(sac_kwargs or {})
        for key in ("ent_coef", "replay_buffer_class", "seed", "gamma"):
            if key in kwargs:
                raise ValueError(
                    f"sac_kwargs must not set {key!r}: the solver fixes it; use the solver's "
                    f"own argument instead."
                )
        policy_kwargs = {"net_arch": list(s.net_arch), **kwargs.pop("policy_kwargs", {})}
        if s.scale_observations:
            if "features_extractor_class" in policy_kwargs:
                raise ValueError("scale_observations=True sets the features extractor; drop "
                                 "features_extractor_class from sac_kwargs['policy_kwargs'].")
            policy_kwargs["features_extractor_class"] = BoxScaler
        algorithm = SAC
        # SB3's SAC has no reward columns and no demonstration terms
        if s.per_agent_critics or s.split_cost_critic or s.demo_bc > 0 or s.demo_value_bound:
            algorithm = DecomposedSAC
            policy_kwargs["n_rewards"] = s.n_rewards
        # Even building the vec env draws from the global numpy stream (SB3): all of it
        # happens on the engine's private streams.
        with self.private_rng():
            self.vec_env = make_vec_env(s.env_factory, n_envs=self.n_envs,
                                        env_kwargs={"constrained": False},
                                        vec_env_cls=DummyVecEnv)
            self.vec_env.seed(self.seed)  # used at the first reset, inside learn()
            self.model = algorithm(
                "MlpPolicy", self.vec_env, learning_rate=s.learning_rate,
                buffer_size=s.buffer_size, learning_starts=s.learning_starts,
                batch_size=s.batch_size, tau=s.tau, gamma=s.gamma, train_freq=s.train_freq,
                gradient_steps=s.gradient_steps, ent_coef=s.ent_coef,
                replay_buffer_class=FeatureReplayBuffer,
                replay_buffer_kwargs={"reward_basis": s.reward_basis,
                                      "cost_basis": s.cost_basis,
                                      "gamma": s.gamma, "absorbing": s.absorbing,
                                      "feature_dtype": s.feature_dtype,
                                      "state_shape": s.spec.state_shape,
                                      "per_agent": s.per_agent_critics,
                                      "split_cost": s.split_cost_critic},
                policy_kwargs=policy_kwargs, device=s.device, seed=None, verbose=0,
                **kwargs,
            )
        self.model.demo_bc, self.model.demo_value_bound = s.demo_bc, s.demo_value_bound
        # Without a logger of its own, every learn() call makes SB3 create an empty
        # SB3-<time> directory in the system temp dir: thousands per table2 run.
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        # Random warm-up actions come from the action space's own generator.
        self.model.action_space.seed(self.seed)
        m, lr = self.model, s.learning_rate
        self.settings = {
            "engine": self.name,
            "learning_rate": float(lr) if isinstance(lr, int | float)
            else getattr(lr, "__qualname__", type(lr).__name__),
            "batch_size": int(m.batch_size), "learning_starts": int(m.learning_starts),
            "tau": float(m.tau), "train_freq": repr(m.train_freq),
            "gradient_steps": int(m.gradient_steps),
            "target_update_interval": int(m.target_update_interval),
            "buffer_size": int(self.replay.buffer_size),
            "feature_dtype": str(self.replay.reward_features.dtype),
        }

    # ---- randomness ---------------------------------------------------------------
    @contextlib.contextmanager
    def private_rng(self) -> Iterator[None]:
        """Run SB3 on the engine's own global-RNG streams; restore the caller's after."""
        cuda = self.device.type == "cuda"
        caller = capture_global_rng(cuda)
        try:
            if self._rng_state is None:
                seed_global_rng(self.seed)
            else:
                restore_global_rng(self._rng_state, cuda)
            yield
        finally:
            self._rng_state = capture_global_rng(cuda)
            restore_global_rng(caller, cuda)

    def reseed(self, seed: int) -> None:
        """After a deep copy: fresh private streams from ``seed`` at the next use; the
        episodes in flight go on, on streams of their own where the env takes one."""
        self.seed = int(seed)
        self._rng_state = None
        self.model.action_space.seed(self.seed)
        for k, env in enumerate(self.vec_env.envs):
            set_rng = protocol_attr(env, "set_rng")
            if callable(set_rng):
                set_rng(np.random.default_rng([self.seed, 3, k]))

    def clone(self) -> SB3Engine:
        return copy.deepcopy(self)

    # ---- training -----------------------------------------------------------------
    @property
    def replay(self) -> FeatureReplayBuffer:
        return self.model.replay_buffer

    @property
    def num_timesteps(self) -> int:
        return int(self.model.num_timesteps)

    @property
    def n_updates(self) -> int:
        return int(self.model._n_updates)

    def learn(self, timesteps: int, bar: Any = None) -> None:
        """SB3's ``learn`` for ``timesteps`` more env steps (a tqdm ``bar`` advanced)."""
        with self.private_rng():
            self.model.learn(total_timesteps=int(timesteps), reset_num_timesteps=False,
                             callback=None if bar is None else _BarCallback(bar))

    def policy_params(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std ``[B, d_a]`` (pre-squash) of the actor at observations
        ``[B, d_o]``."""
        with torch.no_grad():
            o = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            mean, log_std, _ = self.model.actor.get_action_dist_params(o)
        return mean, log_std

    def demo_obs(self, obs: np.ndarray) -> np.ndarray:
        """Raw observations as the replay buffer keeps them (SB3 scales inside the
        networks)."""
        return obs

    def policy_state(self) -> dict[str, torch.Tensor]:
        return copy.deepcopy(self.model.policy.state_dict())

    def load_policy_state(self, state: dict[str, torch.Tensor]) -> None:
        self.model.policy.load_state_dict(state)

    # ---- state --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"global_rng": global_rng_state_dict(self._rng_state),
                "model": model_state_dict(self.model),
                "replay_buffer": self.replay.state_dict(),
                "envs": vec_env_state_dict(self.vec_env)}

    def check_state(self, sd: dict[str, Any]) -> None:
        if "model" not in sd:
            raise ValueError("This SAC state was saved by the lean engine; load it into a "
                             "solver built with engine='lean'.")
        check_model_state(self.model, sd["model"])
        self.replay.check_state(sd["replay_buffer"])
        check_vec_env_state(self.vec_env, sd["envs"])
        global_rng_from_state_dict(sd["global_rng"], self.device.type == "cuda")

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.check_state(sd)
        self._rng_state = global_rng_from_state_dict(sd["global_rng"],
                                                     self.device.type == "cuda")
        load_model_state_dict(self.model, sd["model"])
        self.replay.load_state_dict(sd["replay_buffer"])
        load_vec_env_state_dict(self.vec_env, sd["envs"])

    def close(self) -> None:
        self.vec_env.close()


class _BarCallback(BaseCallback):
    """Advances a tqdm bar by the env steps SB3 takes (no randomness, never stops
    training: the run's numbers are those without it)."""

    def __init__(self, bar: Any) -> None:
        super().__init__()
        self.bar = bar
        self._seen = None

    def _on_training_start(self) -> None:
        self._seen = self.model.num_timesteps

    def _on_step(self) -> bool:
        self.bar.update(self.model.num_timesteps - self._seen)
        self._seen = self.model.num_timesteps
        return True
