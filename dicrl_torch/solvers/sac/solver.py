"""The SAC-style constrained solver, warm-started across calls, with an exact state.

See :mod:`dicrl_torch.solvers.sac` for the design (docs/design.md §5, §7).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from dicrl_torch.features.base import EnvKind
from dicrl_torch.solvers.sac.buffer import FeatureReplayBuffer
from dicrl_torch.solvers.sac.checks import (
    _check_fraction,
    _check_gamma,
    _is_int,
    _weights,
)
from dicrl_torch.solvers.sac.engine_settings import EngineSettings
from dicrl_torch.solvers.sac.episodes import EpisodeSet, episode_set
from dicrl_torch.solvers.sac.features import _basis_dim, _features
from dicrl_torch.solvers.sac.lean import LeanEngine, learn_together
from dicrl_torch.solvers.sac.lineages import Lineage, LineageTraining, step_bar
from dicrl_torch.solvers.sac.protocol import (
    as_continuous,
    check_joint_env,
    make_joint_env,
    protocol_attr,
)
from dicrl_torch.solvers.sac.randomness import (
    generator_state_dict,
    restore_generator,
)
from dicrl_torch.solvers.sac.replay import TransitionStore
from dicrl_torch.solvers.sac.sb3_engine import SB3Engine
from dicrl_torch.solvers.sac.solution import SACSolution
from dicrl_torch.solvers.sac.state import (
    check_tensor,
    optional_array,
    optional_tensor,
    plain,
)

__all__ = ["STATE_FORMAT", "Lineage", "SACConstrainedSolver"]

STATE_FORMAT = "dicrl_torch.SACConstrainedSolver/3"
"""Tag of :meth:`SACConstrainedSolver.state_dict`'s layout."""
_SB3_STATE_FORMAT = "dicrl_torch.SACConstrainedSolver/2"  # before the engines: SB3's only
ENGINES = ("lean", "sb3")


def _from_sb3_format(sd: dict[str, Any]) -> dict[str, Any]:
    """A state of the SB3-only layout as the current one (its engine: ``sb3``)."""
    engine = {k: sd[k] for k in ("global_rng", "model", "replay_buffer", "envs")}
    rest = {k: v for k, v in sd.items() if k not in engine}
    return {**rest, "format": STATE_FORMAT, "settings": {"engine": "sb3", **sd["settings"]},
            "engine": engine}


# Settings that states saved before they existed lack, with the value those states had.
_LATER_SETTINGS = {"demo_bc": 0.0, "demo_value_bound": False, "split_cost_critic": False,
                   "estimate_action": "sampled"}
ESTIMATE_ACTIONS = ("sampled", "mean")


class SACConstrainedSolver(LineageTraining):
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
        sac_kwargs: further keyword arguments for ``stable_baselines3.SAC`` (``engine="sb3"``
            only).
        engine: ``"lean"`` (default: :class:`~dicrl_torch.solvers.sac.lean.LeanEngine`,
            the fast loop) or ``"sb3"`` (:class:`~dicrl_torch.solvers.sac.sb3_engine.SB3Engine`,
            stable-baselines3's loop, the reference the lean one is tested against). The
            same settings give the same algorithm; their random draws differ.
        batched_env: step the game's own batched env (:mod:`dicrl_torch.envs.vector`)
            when its joint env offers one, in the lean engine's training and in
            :meth:`evaluate`; False steps joint envs one by one (the same transitions,
            slower).
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
        engine: str = "lean",
        batched_env: bool = True,
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

        self._eval_rng = np.random.default_rng([self.seed, 1])
        self._eval_gen = torch.Generator(device=self.device)
        self._eval_gen.manual_seed(int(np.random.default_rng([self.seed, 2]).integers(2**62)))
        # Evaluation episodes by (true game, count), built at first use.
        self._eval_envs: dict[tuple[bool, int], EpisodeSet] = {}

        if not isinstance(scale_observations, bool):
            raise ValueError(f"scale_observations must be a bool, got {scale_observations!r}.")
        self.scale_observations = scale_observations
        if not isinstance(per_agent_critics, bool):
            raise ValueError(f"per_agent_critics must be a bool, got {per_agent_critics!r}.")
        self.per_agent_critics = per_agent_critics
        if not isinstance(split_cost_critic, bool):
            raise ValueError(f"split_cost_critic must be a bool, got {split_cost_critic!r}.")
        self.split_cost_critic = split_cost_critic
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {list(ENGINES)} (lean: the fast loop; "
                             f"sb3: stable-baselines3's, the reference), got {engine!r}.")
        if engine == "lean" and sac_kwargs:
            raise ValueError(f"sac_kwargs {sorted(sac_kwargs)} are stable-baselines3 options; "
                             f"they need engine='sb3'.")
        settings = EngineSettings(
            env_factory=env_factory, spec=self.spec, reward_basis=reward_basis,
            cost_basis=cost_basis, seed=self.seed, n_envs=self.n_envs, device=self.device,
            gamma=self.gamma, ent_coef=self.ent_coef, absorbing=self.absorbing,
            learning_rate=learning_rate, buffer_size=buffer_size, batch_size=batch_size,
            learning_starts=learning_starts, tau=tau, train_freq=train_freq,
            gradient_steps=gradient_steps, net_arch=net_arch, feature_dtype=feature_dtype,
            scale_observations=scale_observations, per_agent_critics=per_agent_critics,
            split_cost_critic=split_cost_critic, demo_bc=self.demo_bc,
            demo_value_bound=self.demo_value_bound)
        self.engine = (SB3Engine(settings, sac_kwargs=sac_kwargs) if engine == "sb3"
                       else LeanEngine(settings, batched_env=batched_env))
        self.batched_env = bool(batched_env)
        self.eta: np.ndarray | None = None
        self.cost_weights: np.ndarray | None = None
        self.last_checks: list[dict[str, Any]] = []
        """Per chunk of the last :meth:`solve_keeping_best`: its scores."""

    def clone(self, seed: int) -> SACConstrainedSolver:
        """A copy of this solver — networks, optimisers, replay buffer, envs — with its
        own random streams seeded from ``seed``: learners warm-started from one shared
        pre-trained policy, as all start from the same ``η(0)``, then diverge."""
        if not _is_int(seed):
            raise ValueError(f"seed must be an int, got {seed!r}.")
        twin = copy.deepcopy(self)
        twin.seed = int(seed)
        twin._eval_rng = np.random.default_rng([twin.seed, 1])
        twin._eval_gen.manual_seed(int(np.random.default_rng([twin.seed, 2]).integers(2**62)))
        twin.engine.reseed(twin.seed)
        return twin

    # ---- state --------------------------------------------------------------------
    def _settings(self) -> dict[str, Any]:
        """The construction a state must have been saved under: every argument that
        shapes the state or the training and evaluation that continue from it (not the
        seed: a clone's differs, and the state carries it)."""
        return {
            "reward_features": self.l_r, "cost_features": self.l_c, "n_envs": self.n_envs,
            "gamma": self.gamma, "ent_coef": self.ent_coef, "absorbing": self.absorbing,
            "per_agent_critics": self.per_agent_critics,
            "split_cost_critic": self.split_cost_critic,
            "estimate_action": self.estimate_action,
            "scale_observations": self.scale_observations, "device": self.device.type,
            "demo_fraction": self.demo_fraction, "demo_bc": self.demo_bc,
            "demo_value_bound": self.demo_value_bound,
            "action_margin": self.action_margin,
            "n_eval_episodes": self.n_eval_episodes,
            "env": self.spec.describe(), **self.engine.settings,
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
            "eval_rng": generator_state_dict(self._eval_rng),
            "eval_generator": self._eval_gen.get_state(),
            "engine": self.engine.state_dict(),
        }

    def check_state(self, sd: dict[str, Any]) -> None:
        """Raise a ValueError naming the mismatch unless :meth:`load_state_dict` can load
        ``sd`` (a :meth:`state_dict` of a solver built with the same arguments: basis
        widths, ``n_envs``, buffer size, network shapes, discount, the env's class and
        spaces, ...); changes nothing."""
        if isinstance(sd, dict) and sd.get("format") == _SB3_STATE_FORMAT:
            sd = _from_sb3_format(sd)  # saved before the engines: SB3's pieces at the top
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
        self.engine.check_state(sd["engine"])
        for name, dim in (("eta", self.l_r + 1), ("cost_weights", self.l_c)):
            if sd[name] is not None:
                check_tensor(f"solver {name}", sd[name], (dim,), torch.float64)
        # What load_state_dict reads, read once here so that it cannot fail half-way.
        int(sd["seed"])
        for check in sd["last_checks"]:
            dict(check)
        restore_generator(None, sd["eval_rng"])
        gen_state = self._eval_gen.get_state()
        check_tensor("evaluation torch.Generator", sd["eval_generator"], tuple(gen_state.shape),
                     gen_state.dtype)

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`: afterwards this solver trains, evaluates
        and scores exactly as the one that saved it would have.

        Raises:
            ValueError: ``sd`` is not such a state, or was saved by a solver built
                differently (:meth:`check_state`; the message names the mismatch).
                Nothing is changed then.
        """
        self.check_state(sd)
        if sd.get("format") == _SB3_STATE_FORMAT:
            sd = _from_sb3_format(sd)
        # The engine first: its load may still refuse; the solver's own fields cannot.
        self.engine.seed = int(sd["seed"])
        self.engine.load_state_dict(sd["engine"])
        self.seed = int(sd["seed"])
        self.eta, self.cost_weights = optional_array(sd["eta"]), optional_array(sd["cost_weights"])
        self.last_checks = [dict(c) for c in sd["last_checks"]]
        self._eval_rng = restore_generator(self._eval_rng, sd["eval_rng"])
        self._eval_gen.set_state(sd["eval_generator"])

    # ---- accessors ----------------------------------------------------------------
    @property
    def replay_buffer(self) -> FeatureReplayBuffer | TransitionStore:
        """The engine's replay buffer (its relabelling, demonstrations and penalty basis)."""
        return self.engine.replay

    @property
    def num_timesteps(self) -> int:
        """Env steps taken so far (over all envs)."""
        return int(self.engine.num_timesteps)

    @property
    def n_updates(self) -> int:
        """Gradient updates made so far."""
        return int(self.engine.n_updates)

    def policy_state(self) -> dict[str, torch.Tensor]:
        """A copy of the networks (actor, critics, targets; not the optimisers)."""
        return self.engine.policy_state()

    def load_policy_state(self, state: dict[str, torch.Tensor]) -> None:
        """Set the networks to a :meth:`policy_state`."""
        self.engine.load_policy_state(state)

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
        self.replay_buffer.set_demonstrations(
            demos, self.demo_fraction,
            lambda states: self.engine.demo_obs(self._obs_from_states(states)),
            self.spec.to_policy)

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
        with step_bar(progress, timesteps) as bar:
            self._train(eta, cost_weights, timesteps, bar)
        return self.evaluate(n_eval_episodes,
                             deterministic=self.estimate_action == "mean")

    @staticmethod
    def solve_together(solvers: Sequence[SACConstrainedSolver], etas: Any, cost_weights: Any,
                       timesteps: int, *, n_eval_episodes: int | None = None
                       ) -> list[SACSolution]:
        """``[s.solve(eta, w, timesteps) for s, eta, w in zip(solvers, etas,
        cost_weights)]``, the same numbers, with the lean engines of solvers at the same
        step trained as one ensemble (:func:`~dicrl_torch.solvers.sac.lean.learn_together`):
        the learners of one process, e.g. ``comm=simulated``'s.

        Args:
            solvers: distinct solvers (the learners of a process).
            etas: ``[n, l_r + 1]``, one ``η`` per solver.
            cost_weights: ``[n, l_c]``, one ``ω_c`` per solver.
            timesteps, n_eval_episodes: as :meth:`solve`.
        """
        solvers = list(solvers)
        if len({id(s) for s in solvers}) != len(solvers):
            raise ValueError("solve_together needs distinct solvers (one per learner).")
        for solver, eta, w in zip(solvers, etas, cost_weights, strict=True):
            solver._train(eta, w, 0)
        lean = [s.engine for s in solvers if isinstance(s.engine, LeanEngine)]
        if timesteps > 0:
            learn_together(lean, int(timesteps))
            for s in solvers:
                if not isinstance(s.engine, LeanEngine):
                    s.engine.learn(int(timesteps))
        return [s.evaluate(n_eval_episodes, deterministic=s.estimate_action == "mean")
                for s in solvers]

    def _train(self, eta: Any, cost_weights: Any, timesteps: int, bar: Any = None) -> None:
        """Set the weights (relabelling the buffer) and continue SAC for ``timesteps``
        (advancing a tqdm ``bar`` by the env steps, if given)."""
        if not _is_int(timesteps) or timesteps < 0:
            raise ValueError(f"timesteps must be an int >= 0, got {timesteps!r}.")
        self.set_weights(eta, cost_weights)
        if timesteps > 0:
            self.engine.learn(int(timesteps), bar)

    def _policy_params(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std ``[B, d_a]`` (pre-squash) of the actor at observations
        ``[B, obs_dim]`` (``d_a`` the joint action's size)."""
        return self.engine.policy_params(obs)

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
        key = (bool(true_game), int(n))
        if key not in self._eval_envs:
            self._eval_envs[key] = episode_set(self.env_factory, bool(true_game), n,
                                               self.batched_env)
        episodes = self._eval_envs[key]
        seeds = (self._eval_rng if rng is None else rng).integers(0, 2**31 - 1, size=n)
        obs, current = episodes.reset(seeds)
        n_agents = self.spec.n_agents
        sums_r, sums_c = np.zeros((n, self.l_r)), np.zeros((n, self.l_c))
        lengths = np.zeros(n, dtype=np.int64)
        reached = np.zeros((n, n_agents), dtype=bool)
        violated = np.zeros((n, n_agents), dtype=bool)
        disc = np.ones(n)
        alive = np.ones(n, dtype=bool)
        bonus = 1.0 / (1.0 - self.gamma) if self.absorbing else 1.0
        paths = [[state.copy()] for state in current] if trajectories else None
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
            o, states, terminal, truncated, agents_reached, agents_violated = \
                episodes.step(idx, actions)
            obs[idx], current[idx] = o, states
            reached[idx] |= agents_reached
            violated[idx] |= agents_violated
            lengths[idx] += 1
            if paths is not None:
                for j, i in enumerate(idx):
                    paths[i].append(states[j].copy())
            alive[idx] = ~(terminal | truncated)
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
        self.engine.close()
        for episodes in self._eval_envs.values():
            episodes.close()
        self._env.close()
