"""The solver's lean SAC loop: collect from a vector env, store, update; nothing else.

:class:`LeanEngine` is what :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` trains
with by default (``engine="lean"``). Per vectorised step it acts for every slot with one
actor call, steps the game's own batched env when it has one
(:mod:`dicrl_torch.envs.vector`), stores the ``n_envs`` transitions with their features
(:class:`~dicrl_torch.solvers.sac.replay.TransitionStore`) and, once past
``learning_starts``, makes ``gradient_steps`` updates
(:class:`~dicrl_torch.solvers.sac.update.EnsembleSAC`). SB3's loop
(:class:`~dicrl_torch.solvers.sac.sb3_engine.SB3Engine`, ``engine="sb3"``) does the same
things with the same settings, through its callbacks, ``Monitor`` wrappers, per-step
info dicts and a relabelling of every sampled batch; it stays as the reference the lean
loop is measured and tested against (``python -m dicrl_torch.bench sac``).

Every random draw comes from the engine's own streams (a ``torch.Generator`` for the
networks' initial weights, the policy's noise and the batches; a numpy generator for the
warm-up's uniform actions; each env slot's stream), never from the global ones, so a
learner's numbers do not depend on what else runs in its process.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dicrl_torch.solvers.sac.engine_settings import EngineSettings
from dicrl_torch.solvers.sac.env_list import vector_env_of
from dicrl_torch.solvers.sac.protocol import make_joint_env
from dicrl_torch.solvers.sac.randomness import generator_state_dict, restore_generator
from dicrl_torch.solvers.sac.replay import TransitionStore
from dicrl_torch.solvers.sac.state import check_tensor
from dicrl_torch.solvers.sac.update import Batch, EnsembleSAC

__all__ = ["LeanEngine", "ObservationScale"]

ENGINE_FORMAT = "dicrl_torch.LeanEngine/1"


class ObservationScale:
    """The affine map of a bounded observation box onto ``[-1, 1]`` (entries with
    ``low == high`` to 0), or the identity: observations ``[..., d_o]`` float32."""

    def __init__(self, low: np.ndarray | None = None, high: np.ndarray | None = None) -> None:
        self.identity = low is None
        if not self.identity:
            low, high = np.asarray(low, np.float32).ravel(), np.asarray(high, np.float32).ravel()
            if not (np.isfinite(low).all() and np.isfinite(high).all()):
                raise ValueError("scale_observations needs finite observation bounds; set "
                                 "scale_observations=False for an unbounded Box.")
            half = (high - low) / 2
            self.centre = (high + low) / 2
            self.half_width = np.where(half > 0, half, np.float32(1.0)).astype(np.float32)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        return obs if self.identity else (obs - self.centre) / self.half_width


class LeanEngine:
    """SAC on a vector env with a torch replay store (module docstring).

    Args:
        s: the settings (:class:`EngineSettings`; ``scale_observations``: feed the
            networks observations mapped onto ``[-1, 1]``; batches are gathered on the
            CPU whatever ``device``).
        batched_env: step the game's own batched env when it offers one (False: one
            joint env per slot, the reference behaviour).
    """

    name = "lean"

    def __init__(self, s: EngineSettings, *, batched_env: bool = True) -> None:
        for name, value, low in (("train_freq", s.train_freq, 1),
                                 ("gradient_steps", s.gradient_steps, 0),
                                 ("batch_size", s.batch_size, 1),
                                 ("buffer_size", s.buffer_size, 1),
                                 ("learning_starts", s.learning_starts, 0)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) \
                    or value < low:
                raise ValueError(f"{name} must be an int >= {low} (the lean loop counts "
                                 f"train_freq in vectorised steps), got {value!r}.")
        self.spec, self.device = s.spec, s.device
        self.n_envs = int(s.n_envs)
        self.batch_size, self.learning_starts = int(s.batch_size), int(s.learning_starts)
        self.train_freq, self.gradient_steps = int(s.train_freq), int(s.gradient_steps)
        self.demo_value_bound = bool(s.demo_value_bound)
        self.settings = {"engine": self.name, "learning_rate": float(s.learning_rate),
                         "batch_size": self.batch_size,
                         "learning_starts": self.learning_starts, "tau": float(s.tau),
                         "train_freq": self.train_freq, "gradient_steps": self.gradient_steps,
                         "net_arch": [int(h) for h in s.net_arch],
                         "buffer_size": int(s.buffer_size),
                         "feature_dtype": str(np.dtype(s.feature_dtype))}
        box = s.spec.observation_space
        self.scale = ObservationScale(box.low, box.high) if s.scale_observations \
            else ObservationScale()
        self.vec = vector_env_of(lambda: make_joint_env(s.env_factory, constrained=False),
                                 self.n_envs, batched=batched_env)
        self._seed(s.seed)
        init = torch.Generator().manual_seed(int(np.random.default_rng([s.seed, 7])
                                                 .integers(2**62)))
        obs_dim = int(np.prod(box.shape))
        self.sac = EnsembleSAC(obs_dim=obs_dim, action_dim=s.spec.action_dim,
                               hidden=s.net_arch, n_rewards=s.n_rewards, generators=[init],
                               learning_rate=s.learning_rate, gamma=s.gamma,
                               ent_coef=s.ent_coef, tau=s.tau, demo_bc=s.demo_bc,
                               demo_value_bound=s.demo_value_bound)
        if s.device.type != "cpu":
            self._to_device()
        self.replay = TransitionStore(int(s.buffer_size), obs_dim, s.spec.action_dim,
                                      reward_basis=s.reward_basis, cost_basis=s.cost_basis,
                                      gamma=s.gamma, absorbing=s.absorbing,
                                      state_shape=s.spec.state_shape,
                                      per_agent=s.per_agent_critics,
                                      split_cost=s.split_cost_critic,
                                      feature_dtype=s.feature_dtype)
        self.num_timesteps, self.n_updates, self.vec_steps = 0, 0, 0
        self._obs: np.ndarray | None = None  # [n_envs, d_o] scaled, what the next step acts on

    def _seed(self, seed: int) -> None:
        """The engine's own streams from ``seed`` (a clone's from its own)."""
        self.seed = int(seed)
        self.generator = torch.Generator().manual_seed(
            int(np.random.default_rng([self.seed, 8]).integers(2**62)))
        self.warmup_rng = np.random.default_rng([self.seed, 9])

    def _to_device(self) -> None:
        sac = self.sac
        sac.actor.to(self.device)
        sac.critic.to(self.device)
        sac.actor.params, sac.critic.params = list(sac.actor.parameters()), \
            list(sac.critic.parameters())
        sac.target = [t.to(self.device) for t in sac.target]
        lr_a, lr_c = sac.actor_optimizer.lr, sac.critic_optimizer.lr
        from dicrl_torch.solvers.sac.update import FusedAdam
        sac.actor_optimizer = FusedAdam(sac.actor.params, lr_a)
        sac.critic_optimizer = FusedAdam(sac.critic.params, lr_c)

    # ---- training -----------------------------------------------------------------
    def learn(self, timesteps: int, bar: Any = None) -> None:
        """Continue for ``timesteps`` env steps (whole vectorised steps, as SB3 counts
        them: until ``num_timesteps`` reaches its start plus ``timesteps``), advancing a
        tqdm ``bar`` by the env steps."""
        learn_together([self], timesteps, bar)

    def _start(self) -> None:
        """The first episodes, at the first training step."""
        if self._obs is None:
            seeds = np.random.SeedSequence([self.seed, 10]).generate_state(self.n_envs)
            obs, _ = self.vec.reset([int(s) for s in seeds])
            self._obs = self.scale(obs)

    @property
    def acting(self) -> bool:
        """Whether the next step's actions come from the policy (not the warm-up's)."""
        return self.num_timesteps >= self.learning_starts

    @property
    def updating(self) -> bool:
        """Whether the step just taken is followed by ``gradient_steps`` updates."""
        return self.num_timesteps > self.learning_starts \
            and self.vec_steps % self.train_freq == 0

    def _policy_noise(self) -> torch.Tensor:
        """``[1, n_envs, d_a]`` standard normal draws of the next step's actions."""
        return torch.randn((1, self.n_envs, self.spec.action_dim), generator=self.generator)

    def _collect(self, actions: np.ndarray | None) -> None:
        """One vectorised step with the policy's ``actions`` ``[n_envs, d_a]`` (in
        ``[-1, 1]``; None: the warm-up's uniform ones, as SB3's): step every slot, store
        the transitions."""
        if actions is None:
            actions = self.warmup_rng.uniform(-1.0, 1.0, (self.n_envs, self.spec.action_dim)
                                              ).astype(np.float32)
        step = self.vec.step(self.spec.to_env(actions))
        self.replay.add(self._obs, self.scale(step.final_obs), actions, step.terminated,
                        step.states)
        self._obs = self.scale(step.obs)
        self.num_timesteps += self.n_envs
        self.vec_steps += 1

    def _batch(self) -> tuple[Batch, torch.Tensor]:
        """The next update's batch (``E = 1``) and policy noise ``[1, 2, B, d_a]``."""
        (obs, actions, rewards, next_obs, dones), demo_idx = self.replay.sample(
            self.batch_size, self.generator)
        noise = torch.randn((1, 2, self.batch_size, self.spec.action_dim),
                            generator=self.generator)
        n_demo = 0 if demo_idx is None else len(demo_idx)
        returns = None
        if self.demo_value_bound and n_demo > 0:
            returns = self.replay.demo_returns_of(demo_idx)[None]
        return Batch(obs=obs[None], actions=actions[None], rewards=rewards[None],
                     next_obs=next_obs[None], dones=dones[None], n_demo=n_demo,
                     demo_returns=returns), noise

    # ---- the policy -----------------------------------------------------------------
    def policy_params(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std ``[B, d_a]`` (pre-squash) at raw observations ``[B, d_o]``."""
        o = torch.from_numpy(self.scale(obs)).to(self.device)[None]
        with torch.no_grad():
            mean, log_std = self.sac.actor.dist_params(o)
        return mean[0], log_std[0]

    def demo_obs(self, obs: np.ndarray) -> np.ndarray:
        """Raw observations as the replay store keeps them (scaled)."""
        return self.scale(obs)

    def policy_state(self) -> dict[str, torch.Tensor]:
        return self.sac.policy_state()

    def load_policy_state(self, state: dict[str, torch.Tensor]) -> None:
        self.sac.load_policy_state(state)

    def reseed(self, seed: int) -> None:
        """After a deep copy: streams of its own from ``seed`` (the envs' episodes in
        flight go on, each slot on a stream of its own)."""
        self._seed(seed)
        for k in range(self.n_envs):
            self.vec.set_rng(k, np.random.default_rng([self.seed, 3, k]))

    def clone(self) -> LeanEngine:
        return copy.deepcopy(self)

    # ---- state --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"format": ENGINE_FORMAT, "seed": self.seed,
                "num_timesteps": self.num_timesteps, "n_updates": self.n_updates,
                "vec_steps": self.vec_steps,
                "obs": None if self._obs is None else torch.from_numpy(self._obs.copy()),
                "generator": self.generator.get_state(),
                "warmup_rng": generator_state_dict(self.warmup_rng),
                "networks": self.sac.state_dict(), "replay": self.replay.state_dict(),
                "envs": self.vec.state_dict()}

    def check_state(self, sd: dict[str, Any]) -> None:
        if sd.get("format") != ENGINE_FORMAT:
            raise ValueError(f"This SAC state was saved by another engine ({sd.get('format')!r},"
                             f" this solver's is {ENGINE_FORMAT!r}); load it into a solver "
                             f"built with the same engine.")
        if sd["obs"] is not None:
            check_tensor("training envs' observations", sd["obs"],
                         (self.n_envs, *self.spec.observation_space.shape), torch.float32)
        for key in ("seed", "num_timesteps", "n_updates", "vec_steps"):
            int(sd[key])
        gen = self.generator.get_state()
        check_tensor("SAC generator", sd["generator"], tuple(gen.shape), gen.dtype)
        restore_generator(None, sd["warmup_rng"])
        mine, theirs = self.sac.state_dict(), sd["networks"]
        for group in ("actor", "critic"):
            for k, v in mine[group].items():
                check_tensor(f"SAC {group} {k}", theirs[group].get(k), tuple(v.shape), v.dtype)
        for name in ("target", "actor_optimizer", "critic_optimizer"):
            ours = mine[name] if name == "target" else mine[name]["exp_avgs"] + \
                mine[name]["exp_avg_sqs"] + mine[name]["steps"]
            got = theirs[name] if name == "target" else theirs[name]["exp_avgs"] + \
                theirs[name]["exp_avg_sqs"] + theirs[name]["steps"]
            if len(got) != len(ours):
                raise ValueError(f"SAC {name}: the state holds {len(got)} tensors, this solver "
                                 f"{len(ours)}; load a state saved with the same net_arch.")
            for k, (a, b) in enumerate(zip(ours, got, strict=True)):
                check_tensor(f"SAC {name} tensor {k}", b, tuple(a.shape), a.dtype)
        self.replay.check_state(sd["replay"])
        copy.deepcopy(self.vec).load_state_dict(sd["envs"])

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.check_state(sd)
        self._seed(int(sd["seed"]))
        self.num_timesteps, self.n_updates = int(sd["num_timesteps"]), int(sd["n_updates"])
        self.vec_steps = int(sd["vec_steps"])
        self._obs = None if sd["obs"] is None else sd["obs"].numpy().copy()
        self.generator.set_state(sd["generator"])
        self.warmup_rng = restore_generator(self.warmup_rng, sd["warmup_rng"])
        self.sac.load_state_dict(sd["networks"])
        self.replay.load_state_dict(sd["replay"])
        self.vec.load_state_dict(sd["envs"])

    def close(self) -> None:
        self.vec.close()


# ---- learners that share a process ----------------------------------------------
def _schedule(engine: LeanEngine) -> tuple[Any, ...]:
    """What must be equal for engines to step and update in lock-step as one ensemble."""
    sac = engine.sac
    return (engine.device, engine.n_envs, engine.batch_size, engine.learning_starts,
            engine.train_freq, engine.gradient_steps, engine.num_timesteps,
            engine.vec_steps, engine.n_updates, engine.spec.action_dim,
            engine.replay.demo_rows(engine.batch_size), sac.alpha, sac.gamma, sac.tau,
            sac.demo_bc, sac.demo_value_bound, sac.actor_optimizer.lr,
            sac.critic_optimizer.lr, tuple(p.shape for p in sac.actor.params),
            tuple(p.shape for p in sac.critic.params))


def learn_together(engines: Sequence[LeanEngine], timesteps: int, bar: Any = None) -> None:
    """Continue every engine for ``timesteps`` env steps, their networks as one ensemble.

    Each engine collects from its own envs and samples its own batches with its own
    streams, in the order it would alone; the actor's actions and the updates of all of
    them are computed as one :class:`EnsembleSAC` (their networks stacked, and written
    back after). An ensemble's slices never mix and a batched product of ``E`` slices
    gives each slice the bits it gives alone (``tests/test_sac_update.py``), so every
    engine ends exactly as :meth:`LeanEngine.learn` would leave it. Engines whose
    schedules differ (settings, step counts) are trained one after the other.

    Args:
        engines: the learners' engines (distinct).
        timesteps: env steps for each (over its ``n_envs``).
        bar: a tqdm bar advanced by every engine's env steps, or None.
    """
    engines = list(engines)
    if len(engines) > 1 and len({_schedule(e) for e in engines}) > 1:
        for engine in engines:
            learn_together([engine], timesteps, bar)
        return
    for engine in engines:
        engine._start()
    lead = engines[0]
    sac = lead.sac if len(engines) == 1 else EnsembleSAC.stacked([e.sac for e in engines])
    dev = lead.device
    end = lead.num_timesteps + int(timesteps)
    try:
        while lead.num_timesteps < end:
            actions: list[np.ndarray | None] = [None] * len(engines)
            if lead.acting:
                noise = torch.cat([e._policy_noise() for e in engines]).to(dev)
                obs = torch.from_numpy(np.stack([e._obs for e in engines])).to(dev)
                actions = list(sac.act(obs, noise).cpu().numpy())
            for engine, a in zip(engines, actions, strict=True):
                engine._collect(a)
            if bar is not None:
                bar.update(lead.n_envs * len(engines))
            if lead.updating:
                for _ in range(lead.gradient_steps):
                    batches = [e._batch() for e in engines]
                    sac.update(Batch.stack([b for b, _ in batches], dev),
                               torch.cat([n for _, n in batches]).to(dev))
                    for engine in engines:
                        engine.n_updates += 1
    finally:
        if sac is not lead.sac:
            sac.unstack_into([e.sac for e in engines])
