"""The SAC-style constrained solver, warm-started across calls, with an exact state.

See :mod:`dicrl_torch.solvers.sac` for the design (docs/design.md §5, §7).
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn

from dicrl_torch.features.base import EnvKind
from dicrl_torch.solvers.sac.buffer import FeatureReplayBuffer
from dicrl_torch.solvers.sac.checks import (
    _check_fraction,
    _check_gamma,
    _is_int,
    _weights,
)
from dicrl_torch.solvers.sac.decomposed import DecomposedSAC
from dicrl_torch.solvers.sac.features import BoxScaler, _basis_dim, _features
from dicrl_torch.solvers.sac.protocol import (
    as_continuous,
    check_joint_env,
    make_joint_env,
    protocol_attr,
    step_fields,
)
from dicrl_torch.solvers.sac.randomness import (
    capture_global_rng,
    generator_state_dict,
    global_rng_from_state_dict,
    global_rng_state_dict,
    restore_generator,
    restore_global_rng,
    seed_global_rng,
)
from dicrl_torch.solvers.sac.solution import SACSolution
from dicrl_torch.solvers.sac.state import (
    check_model_state,
    check_tensor,
    check_vec_env_state,
    load_model_state_dict,
    load_vec_env_state_dict,
    model_state_dict,
    optional_array,
    optional_tensor,
    plain,
    vec_env_state_dict,
)

__all__ = ["STATE_FORMAT", "Lineage", "SACConstrainedSolver"]

STATE_FORMAT = "dicrl_torch.SACConstrainedSolver/2"
"""Tag of :meth:`SACConstrainedSolver.state_dict`'s layout."""


# Settings that states saved before they existed lack, with the value those states had.
_LATER_SETTINGS = {"demo_bc": 0.0, "demo_value_bound": False, "split_cost_critic": False,
                   "estimate_action": "sampled"}
ESTIMATE_ACTIONS = ("sampled", "mean")


@dataclass
class Lineage:
    """One lineage of :meth:`SACConstrainedSolver.train_lineages`: its best chunk.

    Attributes:
        restart: the lineage's index (0: the solver itself).
        key: the chunk's rank ``(success, penalised return, -restart, -chunk)``; the
            highest is adopted.
        checks: every chunk's ``{"restart", "timesteps", "penalised_return",
            "success_under_constraints"}``.
        policy_state: the SB3 policy's ``state_dict`` after the best chunk.
        solution: that chunk's :class:`SACSolution` (None when read back from a file).
    """

    restart: int
    key: tuple[float, float, int, int]
    checks: list[dict]
    policy_state: dict[str, torch.Tensor]
    solution: SACSolution | None = None

    def state(self) -> dict[str, Any]:
        """Tensors and plain values only (for ``torch.save`` and a ``weights_only``
        load); the solution stays behind."""
        return {"restart": self.restart, "key": list(self.key), "checks": self.checks,
                "policy_state": self.policy_state}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> Lineage:
        """The lineage of :meth:`state` (without its solution)."""
        s, objective, r, k = state["key"]
        return cls(restart=int(state["restart"]), key=(float(s), float(objective), int(r),
                                                        int(k)),
                   checks=list(state["checks"]), policy_state=dict(state["policy_state"]))


class SACConstrainedSolver:
    """Entropy-regularised SAC on ``r = ω_r·φ_r + λ ω_c·φ_c``, warm-started across calls.

    Example (any PettingZoo ``ParallelEnv`` with ``Box`` actions)::

        def game(constrained):
            return JointAgentEnv(ConstrainedSpread(constrained=constrained),
                                 observation="state")
        solver = SACConstrainedSolver(
            env_factory=game, reward_basis=RandomFourierBasis(n_agents=2, state_dim=4),
            cost_basis=PositionCellBasis(n_agents=2, bounds=..., proximity_radius=0.4),
            seed=0)
        sol = solver.solve(eta, cost_weights, timesteps=20_000)  # eta = [ω_r, λ]
        grad = torch.cat([sol.mu_r - mu_hat, ...]); ll = solver.log_likelihood(demos)

    Args:
        env_factory: builds the joint env (the protocol of the package docstring):
            ``env_factory(constrained=False)`` the nominal game the solver trains and
            evaluates in (the learner knows the nominal dynamics, not the constraints),
            ``env_factory(constrained=True)`` the true game of
            ``evaluate(true_game=True)``. E.g. ``functools.partial(SomeJointEnv,
            max_steps=300)``, or a function wrapping a PettingZoo game in
            :class:`~dicrl_torch.envs.joint.JointAgentEnv`.
        reward_basis: basis of ``φ_r`` (``l_r`` features) over the env's joint states
            ``[..., N, d_s]``, e.g. a :mod:`dicrl_torch.features.continuous` basis.
        cost_basis: basis of ``φ_c`` (``l_c`` features), likewise.
        seed: the solver's only source of randomness (networks, env starts and noise,
            buffer sampling, exploration, evaluation).
        n_envs: parallel envs of the ``DummyVecEnv`` that SAC collects from.
        device: ``"cpu"``, ``"cuda"`` or a ``torch.device`` for the networks.
        gamma: discount.
        ent_coef: the fixed entropy temperature ``α`` (1.0: the MCE model at the scale of
            ``η``; see the module docstring). Must be a positive number.
        absorbing: treat terminal states as absorbing (module docstring).
        n_eval_episodes: rollouts per :meth:`evaluate` (default of :meth:`solve`).
        estimate_action: the actions of :meth:`solve`'s rollouts, which estimate ``μ_r``
            and ``μ_c``: ``"sampled"`` (the MCE policy itself, the paper's model; default)
            or ``"mean"`` (the deployed policy, closer to deterministic experts; on the
            MPE spread it learned fewer true constraints: docs/mpe.md).
        learning_rate, buffer_size, batch_size, learning_starts, tau, train_freq,
            gradient_steps: SAC's (``buffer_size`` counts transitions over all envs).
        net_arch: hidden layers of actor and critics.
        action_margin: demonstrated actions are clipped to ``±(1 - action_margin)`` in
            :meth:`log_likelihood` (the squashed density is infinite at ``±1``).
        feature_dtype: storage dtype of the buffer's features.
        demo_fraction: share of each SAC batch drawn from the demonstrations given to
            :meth:`set_demonstrations` (none are by default), in ``[0, 1)``.
        demo_bc: weight of the Q-filtered demonstration loss on the actor
            (:mod:`~dicrl_torch.solvers.sac.decomposed`): the policy's mean action is pulled
            towards a demonstrated action where its critic rates that action higher, which
            leaves SAC's fixed point unchanged; 0: none. Needs ``demo_fraction > 0``.
        demo_value_bound: bound the critics below by the demonstrated transitions'
            discounted returns under the learned reward (self-imitation's bound,
            :mod:`~dicrl_torch.solvers.sac.decomposed`). Needs ``demo_fraction > 0``.
        scale_observations: feed actor and critics observations mapped onto ``[-1, 1]``
            by the observation space's bounds (:class:`BoxScaler`).
        per_agent_critics: critics with one soft-Q column per agent, each trained on that
            agent's share of the reward (the bases' ``agent_shares()``;
            :mod:`~dicrl_torch.solvers.sac.decomposed`; the fixed point is plain SAC's).
        split_cost_critic: critics with separate soft-Q columns for the reward part
            ``ω_r·φ_r`` and the cost part ``λ ω_c·φ_c`` (per agent too with
            ``per_agent_critics``); their sum is the joint soft Q, so the fixed point is
            plain SAC's. A large penalty then no longer shares one regression with the
            reward.
        sac_kwargs: further keyword arguments for ``stable_baselines3.SAC``.
    """

    # The kind of environment the solver serves: "continuous" (as its bases,
    # features.base.Basis). experiments/config_checks.py refuses it elsewhere.
    env_kind: EnvKind = "continuous"

    def __init__(
        self,
        *,
        env_factory: Callable[..., gym.Env],
        reward_basis: nn.Module,
        cost_basis: nn.Module,
        seed: int,
        n_envs: int = 1,
        device: str | torch.device = "cpu",
        gamma: float = 0.99,
        ent_coef: float = 1.0,
        absorbing: bool = True,
        n_eval_episodes: int = 10,
        estimate_action: str = "sampled",
        learning_rate: float = 3e-4,
        buffer_size: int = 100_000,
        batch_size: int = 256,
        learning_starts: int = 1_000,
        tau: float = 0.005,
        train_freq: int = 1,
        gradient_steps: int = 1,
        net_arch: Sequence[int] = (64, 64),
        action_margin: float = 1e-3,
        feature_dtype: Any = np.float32,
        demo_fraction: float = 0.0,
        demo_bc: float = 0.0,
        demo_value_bound: bool = False,
        scale_observations: bool = False,
        per_agent_critics: bool = False,
        split_cost_critic: bool = False,
        sac_kwargs: dict[str, Any] | None = None,
    ) -> None:
        self.demo_fraction = _check_fraction(demo_fraction, "demo_fraction")
        if isinstance(demo_bc, bool) or not isinstance(demo_bc, int | float | np.floating) \
                or not math.isfinite(demo_bc) or demo_bc < 0:
            raise ValueError(f"demo_bc must be a finite number >= 0, got {demo_bc!r}.")
        if demo_bc > 0 and self.demo_fraction == 0:
            raise ValueError(f"demo_bc={demo_bc} acts on the demonstrated rows of each batch, "
                             f"but demo_fraction is 0; set demo_fraction > 0 (e.g. 0.25) or "
                             f"demo_bc=0.")
        self.demo_bc = float(demo_bc)
        if not isinstance(demo_value_bound, bool):
            raise ValueError(f"demo_value_bound must be a bool, got {demo_value_bound!r}.")
        if demo_value_bound and self.demo_fraction == 0:
            raise ValueError("demo_value_bound acts on the demonstrated rows of each batch, "
                             "but demo_fraction is 0; set demo_fraction > 0 (e.g. 0.25) or "
                             "demo_value_bound=false.")
        self.demo_value_bound = demo_value_bound
        self.l_r = _basis_dim(reward_basis, "reward_basis")
        self.l_c = _basis_dim(cost_basis, "cost_basis")
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        if not _is_int(seed):
            raise ValueError(f"seed must be an int (the solver's only randomness), got {seed!r}.")
        if not _is_int(n_envs) or n_envs < 1:
            raise ValueError(f"n_envs must be a positive int, got {n_envs!r}.")
        if isinstance(ent_coef, str) or isinstance(ent_coef, bool) \
                or not isinstance(ent_coef, int | float | np.floating) \
                or not math.isfinite(ent_coef) or ent_coef <= 0:
            raise ValueError(
                f"ent_coef must be a fixed positive number (the MCE temperature, 1.0 at the "
                f"scale of η), got {ent_coef!r}; automatic tuning ('auto') would change the "
                f"model the rewards are learned for."
            )
        if not _is_int(n_eval_episodes) or n_eval_episodes < 1:
            raise ValueError(f"n_eval_episodes must be a positive int, got {n_eval_episodes!r}.")
        if estimate_action not in ESTIMATE_ACTIONS:
            raise ValueError(f"estimate_action must be one of {list(ESTIMATE_ACTIONS)}, got "
                             f"{estimate_action!r}.")
        self.estimate_action = str(estimate_action)
        if isinstance(action_margin, bool) or not isinstance(action_margin, int | float) \
                or not 0.0 < action_margin < 1.0:
            raise ValueError(f"action_margin must be a float in (0, 1), got {action_margin!r}.")
        self.seed = int(seed)
        self.n_envs = int(n_envs)
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device={device!r} but CUDA is not available; use device='cpu'.")
        self.gamma = _check_gamma(gamma)
        self.ent_coef = float(ent_coef)
        self.absorbing = bool(absorbing)
        self.n_eval_episodes = int(n_eval_episodes)
        self.action_margin = float(action_margin)
        if not callable(env_factory):
            raise ValueError(f"env_factory must be callable as env_factory(constrained=...) "
                             f"-> gymnasium.Env, got {type(env_factory).__name__}.")
        self.env_factory = env_factory
        # Check the env against the protocol now, with a clear error, rather than inside
        # SB3; the probe stays as the reference of the env's spaces and its
        # observations of states (obs_from_states, for demonstrations).
        self._env = make_joint_env(env_factory, constrained=False)
        self.spec = check_joint_env(self._env)
        self._obs_low = self.spec.observation_space.low
        self._obs_high = self.spec.observation_space.high

        self._rng_state: tuple[Any, ...] | None = None
        self._eval_rng = np.random.default_rng([self.seed, 1])
        self._eval_gen = torch.Generator(device=self.device)
        self._eval_gen.manual_seed(int(np.random.default_rng([self.seed, 2]).integers(2**62)))
        self._eval_envs: dict[bool, list[gym.Env]] = {False: [], True: []}

        kwargs = dict(sac_kwargs or {})
        for key in ("ent_coef", "replay_buffer_class", "seed", "gamma"):
            if key in kwargs:
                raise ValueError(
                    f"sac_kwargs must not set {key!r}: the solver fixes it; use the solver's "
                    f"own argument instead."
                )
        if not isinstance(scale_observations, bool):
            raise ValueError(f"scale_observations must be a bool, got {scale_observations!r}.")
        self.scale_observations = scale_observations
        policy_kwargs = {"net_arch": list(net_arch), **kwargs.pop("policy_kwargs", {})}
        if scale_observations:
            if "features_extractor_class" in policy_kwargs:
                raise ValueError("scale_observations=True sets the features extractor; drop "
                                 "features_extractor_class from sac_kwargs['policy_kwargs'].")
            policy_kwargs["features_extractor_class"] = BoxScaler
        if not isinstance(per_agent_critics, bool):
            raise ValueError(f"per_agent_critics must be a bool, got {per_agent_critics!r}.")
        self.per_agent_critics = per_agent_critics
        algorithm = SAC
        if not isinstance(split_cost_critic, bool):
            raise ValueError(f"split_cost_critic must be a bool, got {split_cost_critic!r}.")
        self.split_cost_critic = split_cost_critic
        # SB3's SAC has no reward columns and no demonstration terms
        if per_agent_critics or split_cost_critic or self.demo_bc > 0 or self.demo_value_bound:
            algorithm = DecomposedSAC
            policy_kwargs["n_rewards"] = ((self.spec.n_agents if per_agent_critics else 1)
                                          * (2 if split_cost_critic else 1))
        # Even building the vec env draws from the global numpy stream (SB3): all of it
        # happens on the solver's private streams.
        with self._private_rng():
            self.vec_env = make_vec_env(env_factory, n_envs=self.n_envs,
                                        env_kwargs={"constrained": False},
                                        vec_env_cls=DummyVecEnv)
            self.vec_env.seed(self.seed)  # used at the first reset, inside learn()
            self.model = algorithm(
                "MlpPolicy", self.vec_env, learning_rate=learning_rate,
                buffer_size=buffer_size, learning_starts=learning_starts,
                batch_size=batch_size, tau=tau, gamma=self.gamma, train_freq=train_freq,
                gradient_steps=gradient_steps, ent_coef=self.ent_coef,
                replay_buffer_class=FeatureReplayBuffer,
                replay_buffer_kwargs={"reward_basis": reward_basis, "cost_basis": cost_basis,
                                      "gamma": self.gamma, "absorbing": self.absorbing,
                                      "feature_dtype": feature_dtype,
                                      "state_shape": self.spec.state_shape,
                                      "per_agent": per_agent_critics,
                                      "split_cost": split_cost_critic},
                policy_kwargs=policy_kwargs, device=self.device, seed=None, verbose=0,
                **kwargs,
            )
        self.model.demo_bc, self.model.demo_value_bound = self.demo_bc, self.demo_value_bound
        # Without a logger of its own, every learn() call makes SB3 create an empty
        # SB3-<time> directory in the system temp dir: thousands per table2 run.
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        # Random warm-up actions come from the action space's own generator.
        self.model.action_space.seed(self.seed)
        self.eta: np.ndarray | None = None
        self.cost_weights: np.ndarray | None = None
        self.last_checks: list[dict[str, Any]] = []
        """Per chunk of the last :meth:`solve_keeping_best`: its scores."""

    # ---- randomness ---------------------------------------------------------------
    @contextlib.contextmanager
    def _private_rng(self) -> Iterator[None]:
        """Run SB3 on the solver's own global-RNG streams; restore the caller's after."""
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

    def clone(self, seed: int) -> SACConstrainedSolver:
        """A copy of this solver — networks, optimisers, replay buffer, envs — with its
        own random streams seeded from ``seed``: learners warm-started from one shared
        pre-trained policy, as all start from the same ``η(0)``, then diverge."""
        if not _is_int(seed):
            raise ValueError(f"seed must be an int, got {seed!r}.")
        twin = copy.deepcopy(self)
        twin.seed = int(seed)
        twin._rng_state = None  # fresh private streams from the new seed at next use
        twin._eval_rng = np.random.default_rng([twin.seed, 1])
        twin._eval_gen.manual_seed(int(np.random.default_rng([twin.seed, 2]).integers(2**62)))
        twin.model.action_space.seed(twin.seed)
        # The episodes in flight go on, on streams of their own (not the original's),
        # where the env can take one (the protocol's set_rng).
        for k, env in enumerate(twin.vec_env.envs):
            set_rng = protocol_attr(env, "set_rng")
            if callable(set_rng):
                set_rng(np.random.default_rng([twin.seed, 3, k]))
        return twin

    # ---- state --------------------------------------------------------------------
    def _settings(self) -> dict[str, Any]:
        """The construction a state must have been saved under: every argument that
        shapes the state or the training and evaluation that continue from it (not the
        seed: a clone's differs, and the state carries it)."""
        m = self.model
        lr = m.learning_rate
        return {
            "reward_features": self.l_r, "cost_features": self.l_c, "n_envs": self.n_envs,
            "buffer_size": int(self.replay_buffer.buffer_size), "gamma": self.gamma,
            "ent_coef": self.ent_coef, "absorbing": self.absorbing,
            "per_agent_critics": self.per_agent_critics,
            "split_cost_critic": self.split_cost_critic,
            "estimate_action": self.estimate_action,
            "scale_observations": self.scale_observations, "device": self.device.type,
            "demo_fraction": self.demo_fraction, "demo_bc": self.demo_bc,
            "demo_value_bound": self.demo_value_bound,
            "action_margin": self.action_margin,
            "n_eval_episodes": self.n_eval_episodes,
            "env": self.spec.describe(),
            "learning_rate": float(lr) if isinstance(lr, int | float)
            else getattr(lr, "__qualname__", type(lr).__name__),
            "batch_size": int(m.batch_size), "learning_starts": int(m.learning_starts),
            "tau": float(m.tau), "train_freq": repr(m.train_freq),
            "gradient_steps": int(m.gradient_steps),
            "target_update_interval": int(m.target_update_interval),
            "feature_dtype": str(self.replay_buffer.reward_features.dtype),
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything this solver needs to continue exactly as if it had never stopped,
        as tensors and plain python values only, so that ``torch.save`` then
        ``torch.load(..., weights_only=True)`` round-trips it (SB3's ``save``, which
        pickles, is not used).

        It holds: the seed (a clone's own), ``η`` and ``ω_c``, the last
        :meth:`solve_keeping_best` scores; every random stream (the private copies of
        the global torch / numpy / ``random`` streams SB3 draws from, the evaluation
        ``np.random.Generator`` and ``torch.Generator``, the action space's warm-up
        stream); the SB3 model (actor, critics and target critics, both optimisers,
        ``num_timesteps``, ``_n_updates``, ``_episode_num``, the progress counters,
        ``_last_obs``, ``_last_original_obs``, ``_last_episode_starts``, the episode
        statistics); the replay buffer (its filled rows, ``pos``, ``full``, the relabel
        weights, the demonstrated transitions and their share); and the training envs
        in their current episodes (the game's state, noise stream and step count,
        Monitor records, the seeds of the next reset; any env through
        :func:`~dicrl_torch.solvers.sac.state.object_state_dict` unless it saves
        itself). Load it with :meth:`load_state_dict` into a solver built with the same
        arguments.
        """
        return {
            "format": STATE_FORMAT,
            "settings": self._settings(),
            "seed": self.seed,
            "eta": optional_tensor(self.eta),
            "cost_weights": optional_tensor(self.cost_weights),
            "last_checks": plain(self.last_checks),
            "global_rng": global_rng_state_dict(self._rng_state),
            "eval_rng": generator_state_dict(self._eval_rng),
            "eval_generator": self._eval_gen.get_state(),
            "model": model_state_dict(self.model),
            "replay_buffer": self.replay_buffer.state_dict(),
            "envs": vec_env_state_dict(self.vec_env),
        }

    def check_state(self, sd: dict[str, Any]) -> None:
        """Raise a ValueError naming the mismatch unless :meth:`load_state_dict` can load
        ``sd`` (a :meth:`state_dict` of a solver built with the same arguments: basis
        widths, ``n_envs``, buffer size, network shapes, discount, the env's class and
        spaces, ...); changes nothing."""
        if not isinstance(sd, dict) or sd.get("format") != STATE_FORMAT:
            found = sd.get("format") if isinstance(sd, dict) else type(sd).__name__
            raise ValueError(f"Not a SACConstrainedSolver state (format {found!r}, expected "
                             f"{STATE_FORMAT!r}); pass what SACConstrainedSolver.state_dict() "
                             f"returned.")
        try:
            self._check_state(sd)
        except (KeyError, TypeError, AttributeError, IndexError) as e:
            raise ValueError(f"Malformed SACConstrainedSolver state ({type(e).__name__}: {e}); "
                             f"it was not written by SACConstrainedSolver.state_dict() or has "
                             f"been altered.") from e

    def _check_state(self, sd: dict[str, Any]) -> None:
        mine, theirs = self._settings(), sd["settings"]
        # Settings added after states were first saved: an older state had the default.
        theirs = {**_LATER_SETTINGS, **theirs}
        diff = [f"{k}: state {theirs.get(k)!r}, this solver {v!r}" for k, v in mine.items()
                if theirs.get(k) != v]
        if diff:
            raise ValueError("This SAC solver state was saved by a solver built differently ("
                             + "; ".join(diff) + "); load it into a solver built with the "
                             "same arguments.")
        check_model_state(self.model, sd["model"])
        self.replay_buffer.check_state(sd["replay_buffer"])
        check_vec_env_state(self.vec_env, sd["envs"])
        for name, dim in (("eta", self.l_r + 1), ("cost_weights", self.l_c)):
            if sd[name] is not None:
                check_tensor(f"solver {name}", sd[name], (dim,), torch.float64)
        gen_state = self._eval_gen.get_state()
        check_tensor("evaluation torch.Generator", sd["eval_generator"], tuple(gen_state.shape),
                     gen_state.dtype)
        global_rng_from_state_dict(sd["global_rng"], self.device.type == "cuda")

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`: afterwards this solver trains, evaluates
        and scores exactly as the one that saved it would have.

        Raises:
            ValueError: ``sd`` is not such a state, or was saved by a solver built
                differently (:meth:`check_state`; the message names the mismatch).
                Nothing is changed then.
        """
        self.check_state(sd)
        self.seed = int(sd["seed"])
        self.eta, self.cost_weights = optional_array(sd["eta"]), optional_array(sd["cost_weights"])
        self.last_checks = [dict(c) for c in sd["last_checks"]]
        self._rng_state = global_rng_from_state_dict(sd["global_rng"], self.device.type == "cuda")
        self._eval_rng = restore_generator(self._eval_rng, sd["eval_rng"])
        self._eval_gen.set_state(sd["eval_generator"])
        load_model_state_dict(self.model, sd["model"])
        self.replay_buffer.load_state_dict(sd["replay_buffer"])
        load_vec_env_state_dict(self.vec_env, sd["envs"])

    # ---- accessors ----------------------------------------------------------------
    @property
    def replay_buffer(self) -> FeatureReplayBuffer:
        return self.model.replay_buffer

    @property
    def num_timesteps(self) -> int:
        """Env steps taken so far (over all envs)."""
        return int(self.model.num_timesteps)

    def set_weights(self, eta: Any, cost_weights: Any) -> None:
        """Set ``η = [ω_r, λ]`` (``[l_r + 1]``) and ``ω_c`` (``[l_c]``) for training."""
        eta = _weights(eta, "eta", self.l_r + 1)
        cost_weights = _weights(cost_weights, "cost_weights", self.l_c)
        self.replay_buffer.set_weights(eta[:-1], eta[-1], cost_weights)
        self.eta, self.cost_weights = eta, cost_weights

    def set_demonstrations(self, demos: Any) -> None:
        """Let ``demo_fraction`` of every SAC batch come from ``demos``' transitions,
        relabelled with the current weights like the rest (see
        :meth:`FeatureReplayBuffer.set_demonstrations`). Give a learner only its own
        episodes; ``None`` removes them.

        Args:
            demos: :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations` of the
                env's joint states and actions (or demonstrations with
                ``to_continuous()``), or None.
        """
        if demos is not None:
            demos = as_continuous(demos, self.spec)
        self.replay_buffer.set_demonstrations(demos, self.demo_fraction,
                                              self._obs_from_states, self.spec.to_policy)

    def _obs_from_states(self, states: np.ndarray) -> np.ndarray:
        """The env's joint observations of joint states (the protocol's
        ``obs_from_states``), or a ValueError naming the fix."""
        fn = protocol_attr(self._env, "obs_from_states")
        if not callable(fn):
            raise ValueError(
                f"{self.spec.name} has no obs_from_states(states): scoring or replaying "
                f"demonstrations needs the observation the policy would see in a "
                f"demonstrated joint state; give the env that method (JointAgentEnv has "
                f"it; see the joint-env protocol of dicrl_torch.solvers.sac).")
        return fn(states)

    # ---- solving ------------------------------------------------------------------
    def solve(self, eta: Any, cost_weights: Any, timesteps: int, *,
              n_eval_episodes: int | None = None, progress: str | None = None
              ) -> SACSolution:
        """Continue training on the reward of ``(η, ω_c)``, then evaluate.

        Args:
            eta: ``[l_r + 1]`` ``[ω_r, λ]``.
            cost_weights: ``[l_c]`` ``ω_c``.
            timesteps: further env steps (over all envs); 0 only evaluates.
            n_eval_episodes: rollouts for the estimates (default the solver's).
            progress: a tqdm bar over the env steps with this label (e.g. a warm-up's
                minutes), or None.

        Returns:
            The :class:`SACSolution` of the policy after training.
        """
        with _step_bar(progress, timesteps) as bar:
            self._train(eta, cost_weights, timesteps, bar)
        return self.evaluate(n_eval_episodes,
                             deterministic=self.estimate_action == "mean")

    def solve_keeping_best(self, eta: Any, cost_weights: Any, timesteps: int, *, checks: int,
                           restarts: int = 1, n_eval_episodes: int | None = None,
                           deterministic: bool = False, constraints: Any = None,
                           penalty_basis: Any = None, progress: str | None = None
                           ) -> SACSolution:
        """Train ``timesteps`` in ``checks`` near-equal chunks and end with the networks
        whose policy scored the highest learned objective
        (:meth:`SACSolution.penalised_return`) after any chunk; with ``constraints``, the
        highest :meth:`SACSolution.success_rate_under` them first (ties: the objective).

        SAC's iterates can swing between behaviours from one chunk to the next (seen in
        the paper's continuous experiment; the Table 2 notes in docs/); this keeps the
        best one seen, as an evaluation callback that saves the best model does. With
        ``restarts`` > 1 the same is done from this solver's current state by
        ``restarts - 1`` clones as well (:meth:`clone`, seeds drawn from this
        solver's), whose lineages diverge, and the best chunk of any of them is kept: more
        independent chances when one lineage never settles. The score is the learner's
        own: its ``(η, ω_c)``, rolled out in the solver's game (the nominal one by default);
        no true constraint is consulted.

        Args:
            eta, cost_weights, n_eval_episodes: as :meth:`solve` (rollouts per score).
            timesteps: env steps per restart (>= ``checks``).
            checks: number of chunks per restart, each followed by a score; 1 (with one
                restart) is :meth:`solve`.
            restarts: independent continuations from the current state (1: this solver's).
            deterministic: score the mean-action policy (how it is deployed).
            constraints: ``[l_c]`` bool, the learner's constraint set (e.g. its
                ``ω_c ≥ 0.5``), or None.
            penalty_basis: train on the penalty ``λ ω_c · φ`` with ``φ`` this basis's
                features (``l_c`` of them, e.g. the cost basis grown by a margin:
                ``CellOccupancyCostBasis.dilated``) for this solve only
                (:meth:`FeatureReplayBuffer.set_penalty_basis`); the scores and the
                returned estimates keep the cost basis. None: the cost basis.
            progress: a tqdm bar over every lineage's env steps with this label (the
                best score so far beside it), or None.

        Returns:
            The best chunk's :class:`SACSolution` (its rollouts gave the score); this
            solver's networks are left as that chunk's. Every chunk's ``{"restart",
            "timesteps", "penalised_return", "success_under_constraints"}`` (the last None
            without ``constraints``) is left in ``self.last_checks``.
        """
        lineages = self.train_lineages(
            eta, cost_weights, timesteps, checks=checks, restarts=restarts,
            n_eval_episodes=n_eval_episodes, deterministic=deterministic,
            constraints=constraints, penalty_basis=penalty_basis, progress=progress)
        # A clone's solution: its policy now lives here (the clone is closed).
        return replace(self.adopt_best(lineages).solution, solver=self)

    def train_lineages(self, eta: Any, cost_weights: Any, timesteps: int, *, checks: int,
                       restarts: int = 1, lineages: Sequence[int] | None = None,
                       n_eval_episodes: int | None = None, deterministic: bool = False,
                       constraints: Any = None, penalty_basis: Any = None,
                       progress: str | None = None) -> list[Lineage]:
        """:meth:`solve_keeping_best`'s lineages ``lineages`` (default every one of
        ``range(restarts)``), each trained and scored chunk by chunk, without adopting
        any: :meth:`adopt_best` does that. Lineage 0 is this solver itself (trained
        last, so that the clones start from its current state), lineage ``r > 0`` the
        clone seeded by the ``r``-th seed drawn from this solver's seed.

        As every lineage depends only on the solver's state and its own seed, equal
        solvers in several processes can each train a share of them: :meth:`adopt_best`
        of all the lineages (read back with :meth:`Lineage.from_state`), in the process
        that trained lineage 0, leaves that solver as one :meth:`solve_keeping_best`
        would have (docs/design.md §7, the shared warm-up).

        Args: as :meth:`solve_keeping_best`; ``progress`` counts the steps of the
        lineages trained here.

        Returns:
            One :class:`Lineage` per lineage trained, in increasing order.
        """
        if not _is_int(checks) or checks < 1:
            raise ValueError(f"checks must be a positive int, got {checks!r}.")
        if not _is_int(timesteps) or timesteps < checks:
            raise ValueError(f"timesteps must be an int >= checks={checks}, got "
                             f"{timesteps!r}.")
        if not _is_int(restarts) or restarts < 1:
            raise ValueError(f"restarts must be a positive int, got {restarts!r}.")
        mine = list(range(restarts)) if lineages is None else [int(r) for r in lineages]
        if not mine or sorted(set(mine)) != sorted(mine) or min(mine) < 0 \
                or max(mine) >= restarts:
            raise ValueError(f"lineages must be distinct ints in [0, restarts={restarts}), "
                             f"got {lineages!r}.")
        chunks = np.diff(np.linspace(0, int(timesteps), checks + 1).round().astype(int))
        # Clone seeds come from this solver's seed, so a run is reproducible. The clones
        # run first, one at a time (each holds a copy of the replay buffer), while this
        # solver still has the state they start from; it runs last as restart 0.
        seeds = np.random.SeedSequence([self.seed, 4]).generate_state(restarts - 1)
        order = [r for r in sorted(mine) if r] + [0] * (0 in mine)
        # Set before the clones copy the buffer; every later solve trains on φ_c again.
        self.replay_buffer.set_penalty_basis(penalty_basis)
        try:
            with _step_bar(progress, len(order) * int(timesteps)) as bar:
                done = [self._lineage(r, seeds, eta, cost_weights, chunks, n_eval_episodes,
                                      deterministic, constraints, bar) for r in order]
        finally:
            self.replay_buffer.set_penalty_basis(None)
        return sorted(done, key=lambda lineage: lineage.restart)

    def _lineage(self, r: int, seeds: np.ndarray, eta: Any, cost_weights: Any,
                 chunks: np.ndarray, n_eval_episodes: int | None, deterministic: bool,
                 constraints: Any, bar: Any) -> Lineage:
        """Lineage ``r`` of :meth:`train_lineages` (0: this solver, else a clone of
        ``seeds[r - 1]``): its best chunk and every chunk's scores."""
        solver = self if r == 0 else self.clone(int(seeds[r - 1]))
        best = None
        checks = []
        for k, steps in enumerate(chunks):
            solver._train(eta, cost_weights, int(steps), bar)
            solution = solver.evaluate(n_eval_episodes, deterministic=deterministic)
            objective = solution.penalised_return()[0]
            success = (None if constraints is None
                       else solution.success_rate_under(constraints))
            checks.append({"restart": r, "timesteps": solver.num_timesteps,
                           "penalised_return": objective,
                           "success_under_constraints": success})
            # Ties go to the earlier restart, then the earlier chunk.
            key = (0.0 if success is None else success, objective, -r, -k)
            if best is None or key > best.key:
                best = Lineage(restart=r, key=key, checks=checks, solution=solution,
                               policy_state=copy.deepcopy(solver.model.policy.state_dict()))
            if bar is not None:  # the best so far: its success rate, its objective
                bar.set_postfix(lineage=r, best_objective=f"{best.key[1]:.1f}",
                                **({} if success is None
                                   else {"best_success": f"{best.key[0]:.2f}"}),
                                refresh=False)
        if solver is not self:
            solver.close()
        return best

    def adopt_best(self, lineages: Sequence[Lineage]) -> Lineage:
        """Load the policy of the best-scored chunk of ``lineages`` (every lineage of a
        :meth:`train_lineages` split, see there) into this solver, leave every chunk's
        scores in ``self.last_checks`` (by restart, then chunk) and return that lineage."""
        if not lineages or len({lineage.restart for lineage in lineages}) != len(lineages):
            raise ValueError(f"adopt_best needs distinct lineages, got restarts "
                             f"{[lineage.restart for lineage in lineages]}.")
        best = max(lineages, key=lambda lineage: lineage.key)
        self.model.policy.load_state_dict(best.policy_state)
        self.last_checks = [c for lineage in sorted(lineages, key=lambda x: x.restart)
                            for c in lineage.checks]
        return best

    def _train(self, eta: Any, cost_weights: Any, timesteps: int, bar: Any = None) -> None:
        """Set the weights (relabelling the buffer) and continue SAC for ``timesteps``
        (advancing a tqdm ``bar`` by the env steps, if given)."""
        if not _is_int(timesteps) or timesteps < 0:
            raise ValueError(f"timesteps must be an int >= 0, got {timesteps!r}.")
        self.set_weights(eta, cost_weights)
        if timesteps > 0:
            with self._private_rng():
                self.model.learn(total_timesteps=int(timesteps), reset_num_timesteps=False,
                                 callback=None if bar is None else _BarCallback(bar))

    def _policy_params(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std ``[B, d_a]`` (pre-squash) of the actor at observations
        ``[B, obs_dim]`` (``d_a`` the joint action's size)."""
        actor = self.model.actor
        with torch.no_grad():
            o = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            mean, log_std, _ = actor.get_action_dist_params(o)
        return mean, log_std

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Joint actions ``[B, d_a]`` in the env's action box for joint observations
        ``[B, obs_dim]``, sampled with the solver's evaluation generator (tanh of the
        mean when ``deterministic``), mapped from SAC's ``[-1, 1]`` onto the box (as SB3
        does; no change for a ``[-1, 1]`` box)."""
        mean, log_std = self._policy_params(obs)
        if deterministic:
            return self.spec.to_env(torch.tanh(mean).cpu().numpy())
        eps = torch.randn(mean.shape, generator=self._eval_gen, device=self.device)
        return self.spec.to_env(torch.tanh(mean + log_std.exp() * eps).cpu().numpy())

    def evaluate(self, n_episodes: int | None = None, *, deterministic: bool = False,
                 true_game: bool = False, rng: np.random.Generator | None = None,
                 trajectories: bool = False, actor: Callable | None = None,
                 progress: str | None = None) -> SACSolution:
        """Roll out the current policy for ``n_episodes`` episodes and estimate the
        discounted feature sums (absorbing terminal, as in training).

        Episodes are stepped in lock-step so the actor runs once per step on a batch.

        Args:
            n_episodes: rollouts (default the solver's ``n_eval_episodes``).
            deterministic: act with ``tanh`` of the mean.
            true_game: roll out in the true game, ``env_factory(constrained=True)``
                (e.g. violators freeze: the metrics SR and CVR), not the solver's nominal
                game.
            rng: draws the episodes' env seeds (default the solver's own evaluation
                stream); pass a fresh seeded generator to compare policies on common
                random numbers.
            trajectories: also keep each episode's joint states ``[L+1, N, d_s]`` (for
                figures).
            actor: act with ``actor(states [b, N, d_s], active [b, N], episodes [b])``
                instead of this solver's policy: the env actions ``[b, d_a]`` of the
                episodes ``episodes`` (indices among the ``n``) from their current joint
                states, ``active`` the agents still flying (neither arrived nor, in the
                true game, frozen); e.g. a planner per episode
                (:mod:`dicrl_torch.solvers.planning`). ``deterministic`` is then unused.
            progress: a tqdm bar over finished episodes with this label (e.g. for a
                planner's minutes of rollouts), or None.
        """
        n = self.n_eval_episodes if n_episodes is None else n_episodes
        if not _is_int(n) or n < 1:
            raise ValueError(f"n_episodes must be a positive int, got {n!r}.")
        cache = self._eval_envs[bool(true_game)]
        while len(cache) < n:
            cache.append(make_joint_env(self.env_factory, constrained=bool(true_game)))
        envs = cache[:n]
        seeds = (self._eval_rng if rng is None else rng).integers(0, 2**31 - 1, size=n)
        starts = [env.reset(seed=int(s)) for env, s in zip(envs, seeds, strict=True)]
        obs = np.stack([o for o, _ in starts])
        n_agents = self.spec.n_agents
        sums_r, sums_c = np.zeros((n, self.l_r)), np.zeros((n, self.l_c))
        lengths = np.zeros(n, dtype=np.int64)
        reached = np.zeros((n, n_agents), dtype=bool)
        violated = np.zeros((n, n_agents), dtype=bool)
        disc = np.ones(n)
        alive = np.ones(n, dtype=bool)
        bonus = 1.0 / (1.0 - self.gamma) if self.absorbing else 1.0
        paths = [[np.array(info["state"])] for _, info in starts] if trajectories else None
        current = np.stack([np.array(info["state"], dtype=np.float64) for _, info in starts])
        bar = None
        if progress is not None:
            from tqdm.auto import tqdm
            bar = tqdm(total=n, desc=progress, unit="episode", leave=False)
        while alive.any():
            idx = np.flatnonzero(alive)
            if actor is None:
                actions = self.act(obs[idx], deterministic)
            else:
                flying = ~(reached[idx] | (violated[idx] if true_game else False))
                actions = np.asarray(actor(current[idx], flying, idx))
            states = np.zeros((len(idx), *self.spec.state_shape))
            terminal = np.zeros(len(idx), dtype=bool)
            for j, i in enumerate(idx):
                o, _, term, trunc, info = envs[i].step(actions[j])
                state, agents_reached, agents_violated = step_fields(info)
                obs[i], states[j], terminal[j] = o, state, term
                current[i] = state
                reached[i] |= agents_reached
                violated[i] |= agents_violated
                lengths[i] += 1
                if paths is not None:
                    paths[i].append(np.array(state))
                if term or trunc:
                    alive[i] = False
            w = disc[idx] * np.where(terminal, bonus, 1.0)
            sums_r[idx] += w[:, None] * _features(self.reward_basis, states)
            sums_c[idx] += w[:, None] * _features(self.cost_basis, states)
            disc[idx] *= self.gamma
            if bar is not None:
                bar.update(int(len(idx) - alive[idx].sum()))
                bar.set_postfix(step=int(lengths.max()), refresh=False)
        if bar is not None:
            bar.close()
        return SACSolution(
            reward_sums=torch.from_numpy(sums_r), cost_sums=torch.from_numpy(sums_c),
            lengths=torch.from_numpy(lengths), reached=torch.from_numpy(reached),
            violated=torch.from_numpy(violated),
            eta=None if self.eta is None else torch.from_numpy(self.eta.copy()),
            cost_weights=None if self.cost_weights is None
            else torch.from_numpy(self.cost_weights.copy()),
            timesteps=self.num_timesteps, solver=self,
            paths=None if paths is None else [np.stack(p) for p in paths],
        )

    # ---- likelihood ---------------------------------------------------------------
    def log_likelihood(self, demos: Any, *,
                       per_episode: bool = False) -> float | torch.Tensor:
        """Discounted log-likelihood ``Σ_episodes Σ_t γ^t ln π(a_t | s_t)`` of
        demonstrations.

        ``π`` is the SAC policy's squashed Gaussian density on ``[-1, 1]^{N d_a}`` (env
        actions mapped there first, as SB3 does): per action dimension
        ``ln N(atanh a; μ, σ) − ln(1 − a²)``. An agent's dimensions count only while it
        acts (``demos.acting_mask()``: ``t < agent_lengths``): after it left the episode
        its recorded actions are ignored by the env, and as the dimensions are
        independent, dropping them is the exact marginal. Actions are clipped to
        ``±(1 − action_margin)``.

        Args:
            demos: :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations` of the
                env's joint states and actions (or demonstrations with
                ``to_continuous()``).
            per_episode: return the ``[m]`` float64 per-episode values instead of their
                sum.

        Returns:
            The sum over episodes (float), or ``[m]`` with ``per_episode``.

        Raises:
            ValueError: ``demos`` are not demonstrations of this env's shapes (the
                message names the field and the fix).
        """
        demos = as_continuous(demos, self.spec)
        m, T, n_agents = demos.n_episodes, demos.horizon, demos.n_agents
        obs = np.clip(self._obs_from_states(demos.states[:, :T]), self._obs_low,
                      self._obs_high)
        mean, log_std = self._policy_params(obs.reshape(m * T, -1))
        mean, log_std = mean.double().cpu(), log_std.double().cpu()
        bound = 1.0 - self.action_margin
        actions = self.spec.to_policy(np.array(demos.actions).reshape(m * T, -1))
        a = torch.from_numpy(actions).clamp(-bound, bound)  # [m*T, N d_a]
        u = torch.atanh(a)
        logp = (torch.distributions.Normal(mean, log_std.exp()).log_prob(u)
                - torch.log1p(-a * a))  # [m*T, N d_a]
        logp = logp.reshape(m, T, n_agents, -1).sum(-1)  # [m, T, N] per agent
        acting = torch.from_numpy(demos.acting_mask())  # [m, T, N]
        disc = self.gamma ** torch.arange(T, dtype=torch.float64)
        per = (torch.where(acting, logp, 0.0).sum(-1) * disc).sum(1)  # [m]
        return per if per_episode else float(per.sum())

    def close(self) -> None:
        """Close the training, evaluation and reference envs."""
        self.vec_env.close()
        for env in self._eval_envs[False] + self._eval_envs[True] + [self._env]:
            env.close()


# ---- progress ---------------------------------------------------------------------
@contextlib.contextmanager
def _step_bar(label: str | None, total: int) -> Iterator[Any]:
    """A tqdm bar of ``total`` env steps labelled ``label`` (closed on exit), or None
    without a label."""
    if label is None:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=int(total), desc=label, unit="step", leave=False)
    try:
        yield bar
    finally:
        bar.close()


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
