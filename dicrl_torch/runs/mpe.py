"""The constrained MPE ``simple_spread`` as a run's task: the first
third-party game through the same runner and trainer as the grid world and the drones.

The game is :class:`~dicrl_torch.envs.mpe.ConstrainedSpread` (mpe2's ``simple_spread``
with fixed landmarks behind a forbidden disc and a minimum inter-agent distance; in the
true game a violator freezes), wrapped for the SAC solver by
:class:`~dicrl_torch.envs.joint.JointAgentEnv` with ``observation="state"``: the policy
reads the flattened joint state ``[N * 4]`` (``x, y, vx, vy`` per agent), and the
feature bases the joint state ``[N, 4]``. The steps (shared with every continuous task,
:class:`~dicrl_torch.runs.continuous.SACTask`):

1. **Experts.** :class:`~dicrl_torch.demos.mpe_experts.ViaPointController` (around the disc in
   lanes, start delays that keep the agents apart) flown in the true game and recorded
   with :func:`~dicrl_torch.demos.continuous.record_demonstrations` (joint states of
   ``env.state()``); an episode is kept only if the env's own verdict is a success
   without violation (:meth:`~dicrl_torch.envs.mpe.ConstrainedSpread.task_success`), so
   the demonstrations respect the true constraints. Or the user's own demonstrations
   (a :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations` or its ``.npz``),
   checked against the env's spaces. Split over the learners by ``split``.
2. One SAC solver is warmed up on ``η(0), ω_c(0)``; learners, C-ICRL and M(C)E-greedy
   train clones of it. The learned set is ``ω_c,j >= threshold``.
3. **Rows.** A last solve on the learned ``(η̄, ω_c)``, then ``eval_episodes`` rollouts
   in the TRUE game (mean and sampled actions, the same starts for every row):

   - **SR**, task success: at the episode's end every landmark lies within ``r`` of a
     distinct agent and no agent violated a constraint during the episode, with ``r =``
     :data:`dicrl_torch.envs.mpe.SUCCESS_RADIUS` (0.1, mpe2's capture radius of
     ``simple_spread``), the env's own definition
     (:meth:`~dicrl_torch.envs.mpe.ConstrainedSpread.task_success`,
     :func:`~dicrl_torch.envs.mpe.landmarks_covered`);
   - **CVR**: the share of agents that violated a true constraint (entered the disc, or
     came closer than ``min_distance`` to another active agent), over episodes and
     agents;
   - **FPR / FNR** of the learned set against the cost basis's true constraint features
     (for :class:`~dicrl_torch.features.continuous.PositionCellBasis` the cells
     overlapping the disc plus the proximity feature, computed from the env's layout);
     ``FNR_required`` the misses among the *required* ones (below).

   Reference rows: the experts (``Experts (ground truth)``) and the nominal controller
   (``Experts (nominal)``, straight to the landmarks) flown in the true game from the
   same starts.
4. **Identifiability** of the true constraint features (``results.json``'s
   ``identifiability``): *demonstrated*, accrued by the demonstrations (or positive on
   the start distribution's support); *required*, accrued by
   :class:`~dicrl_torch.demos.mpe_experts.NominalController` 's rollouts from the demonstrations'
   starts but not by the demonstrations (the data show the experts avoiding what an
   unconstrained team uses); *undetermined*, neither (no data can tell it from a free
   feature). A simple, rollout-based version of the grid's classes (docs/design.md §6).
5. **Figures.** ``spread_demonstrations``: the arena, the demonstrations and the true
   constraint cells; per row a constraint map with the learned cells (hatched) and up to
   9 evaluation rollouts.

:func:`build_mpe_task` builds the task from plain keyword arguments (the Hydra entry
point's dispatch of ``env=mpe_spread``, or a script).
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from dicrl_torch.algos.identifiability import Identifiability, fnr_required
from dicrl_torch.demos.continuous import (
    ContinuousDemonstrations,
    load_continuous_demonstrations,
    record_demonstrations,
)
from dicrl_torch.demos.mpe_experts import NominalController, ViaPointController, run_episode
from dicrl_torch.envs.joint import JointAgentEnv
from dicrl_torch.envs.mpe import (
    SUCCESS_RADIUS,
    ConstrainedSpread,
    SpreadLayout,
    landmarks_covered,
    render_spread,
    sample_starts,
)
from dicrl_torch.envs.mpe.layout import MAX_SPEED, in_disc, pairwise_too_close
from dicrl_torch.features.continuous import ContinuousFeatureBasis, PositionCellBasis
from dicrl_torch.features.mpe import LandmarkRewardBasis
from dicrl_torch.metrics import true_constraints_of
from dicrl_torch.region import RegionTruth
from dicrl_torch.runs.continuous import SACTask, derived_seed
from dicrl_torch.runs.results import REGION_COLUMNS
from dicrl_torch.runs.task import Rollouts

__all__ = ["ANNOTATIONS", "ControllerPolicy", "MPETask", "build_mpe_task",
           "spread_joint_env", "spread_start_states",
           "spread_success"]

ANNOTATIONS = ("FNR_required", "n_demonstrated", "n_required", "n_undetermined",
               "contradictions")
"""What :meth:`MPETask.annotate` adds to every learned row (the grid's keys)."""
STATE_DIM = 4
"""``d_s`` of ConstrainedSpread's joint state: ``x, y, vx, vy`` per agent."""


# ------------------------------------------------------------------ the game's pieces
def spread_joint_env(constrained: bool = False, *, layout: SpreadLayout | None = None,
                     **env_kwargs: Any) -> JointAgentEnv:
    """The SAC solver's joint env of the constrained spread (its ``env_factory`` is a
    ``functools.partial`` of this, picklable): ``ConstrainedSpread(layout=layout,
    constrained=constrained, **env_kwargs)`` as one gymnasium agent whose observation
    is the flattened joint state ``[N * 4]`` and whose ``info["state"]`` is ``[N, 4]``
    (``env.state()``; demonstrations recorded with ``use_state=True`` hold the same)."""
    return JointAgentEnv(ConstrainedSpread(layout=layout, constrained=constrained,
                                           **env_kwargs),
                         observation="state", use_state=True)


class ControllerPolicy:
    """A :class:`~dicrl_torch.envs.mpe.ConstrainedSpread` controller (``reset(state)``,
    ``act(state, active) -> [N, 2]``) as a
    :func:`~dicrl_torch.demos.continuous.record_demonstrations` policy: a fresh
    controller ``make(env)`` is reset on the joint state at every episode's first step.

    Args:
        make: ``env -> controller``, e.g. ``ViaPointController`` or
            ``functools.partial(ViaPointController, clearance=0.25)``.
    """

    def __init__(self, make: Callable[[ConstrainedSpread], Any]) -> None:
        if not callable(make):
            raise TypeError(f"make must build a controller from the env, got "
                            f"{type(make).__name__}.")
        self.make = make
        self._controller: Any = None

    def __call__(self, observations: Mapping[str, Any], env: ConstrainedSpread
                 ) -> dict[str, np.ndarray]:
        if env.timestep == 0:  # the episode's first step: plan from its start
            self._controller = self.make(env)
            self._controller.reset(env.state())
        u = self._controller.act(env.state(), env.active)  # [N, 2]
        return {a: u[env.possible_agents.index(a)] for a in env.agents}


def spread_success(positions: np.ndarray, violated: np.ndarray,
                   layout: SpreadLayout) -> np.ndarray:
    """Task success per episode, the env's definition
    (:meth:`~dicrl_torch.envs.mpe.ConstrainedSpread.task_success`): every landmark within
    :data:`~dicrl_torch.envs.mpe.SUCCESS_RADIUS` of a distinct agent at the end, and no
    violation in the episode.

    Args:
        positions: ``[n, N, 2]`` the agents' final positions.
        violated: ``[n, N]`` bool, agents that violated during the episode.
        layout: the game's geometry (its landmarks).

    Returns:
        ``[n]`` bool.
    """
    positions, violated = np.asarray(positions), np.asarray(violated, dtype=bool)
    return np.array([landmarks_covered(p, layout.landmark_array, SUCCESS_RADIUS)
                     and not v.any() for p, v in zip(positions, violated, strict=True)],
                    dtype=bool)


def spread_start_states(layout: SpreadLayout, n: int = 4096, seed: int = 0) -> np.ndarray:
    """``[n, N, 4]`` joint states drawn from the game's start distribution (at rest,
    positions as :func:`~dicrl_torch.envs.mpe.sample_starts` draws them): a sample of
    P0's support for :meth:`~dicrl_torch.algos.models.SACLearnerModel.start_features`
    (the cells of the start region; no proximity, as starts are apart)."""
    rng = np.random.default_rng(seed)
    pos = np.stack([sample_starts(layout, rng) for _ in range(n)])  # [n, N, 2]
    return np.concatenate([pos, np.zeros_like(pos)], -1)


def _check_basis(basis: Any, role: str, states: np.ndarray) -> None:
    """``basis`` must compute ``[..., dim]`` features in ``[0, max_value]`` of the
    game's joint states ``states`` ``[..., N, 4]``; else a ValueError naming the basis,
    what it did and the fix (before any solve, not deep inside SAC)."""
    label = getattr(basis, "label", type(basis).__name__)
    dim, top = getattr(basis, "dim", None), getattr(basis, "max_value", None)
    if not isinstance(basis, torch.nn.Module) or dim is None:
        raise ValueError(f"{role} must be a feature basis (an nn.Module with .dim, e.g. a "
                         f"dicrl_torch.features.continuous basis), got "
                         f"{type(basis).__name__}.")
    try:
        with torch.no_grad():
            phi = basis(torch.from_numpy(np.array(states, dtype=np.float64)))
    except (ValueError, TypeError, RuntimeError) as e:
        raise ValueError(f"{role} {label} cannot compute features of the game's joint "
                         f"states [..., N={states.shape[-2]}, d_s={states.shape[-1]}] "
                         f"(x, y, vx, vy per agent): {e}") from e
    if not isinstance(phi, torch.Tensor) or tuple(phi.shape) != (*states.shape[:-2], dim):
        shape = tuple(phi.shape) if isinstance(phi, torch.Tensor) else type(phi).__name__
        raise ValueError(f"{role} {label} returned {shape} for states of shape "
                         f"{states.shape}, expected {(*states.shape[:-2], dim)} (dim = "
                         f"{dim} features per joint state); fix its dim or its output "
                         f"layer.")
    if top is not None and not bool(((phi >= 0) & (phi <= top)).all()):
        raise ValueError(f"{role} {label} returned values in [{float(phi.min()):.4g}, "
                         f"{float(phi.max()):.4g}], outside [0, max_value={top}]: the "
                         f"features must be bounded and non-negative; rescale them (e.g. "
                         f"end the network with {_BOUNDED_END[role]}).")


# How a network's output layer keeps its features in [0, max_value]: a cost feature needs
# exact zeros (its constraint set is its support), a reward feature need not.
_BOUNDED_END = {"cost_basis": "a ReLU clipped to max_value, torch.clamp(x, 0, max_value), "
                              "so that each feature is 0 outside a region: a sigmoid is "
                              "positive everywhere and can be no constraint",
                "reward_basis": "ScaledSigmoid(max_value)"}


def _check_geometry(reward_basis: Any, cost_basis: Any, layout: SpreadLayout) -> None:
    """A basis that carries the game's geometry must carry this layout's: landmarks of a
    :class:`LandmarkRewardBasis`, the arena of a :class:`PositionCellBasis` (its cells
    and its ground truth are laid over it)."""
    if isinstance(reward_basis, LandmarkRewardBasis) and not np.allclose(
            reward_basis.landmarks, layout.landmark_array):
        raise ValueError(f"reward_basis rewards landmarks at {list(reward_basis.landmarks)}, "
                         f"but the game's are {list(layout.landmarks)}; build it with "
                         f"landmarks=layout.landmarks.")
    h = layout.arena_half_width
    if isinstance(cost_basis, PositionCellBasis) and not np.allclose(
            cost_basis.bounds, ((-h, h), (-h, h))):
        raise ValueError(f"cost_basis lays its cells over {cost_basis.bounds}, but the "
                         f"game's walls are at ±{h}; build it with bounds=(({-h}, {h}), "
                         f"({-h}, {h})).")


def _check_demonstrations(demos: ContinuousDemonstrations, spec: Any,
                          env: ConstrainedSpread) -> ContinuousDemonstrations:
    """``demos`` against the game: joint states ``[N, 4]``, actions ``[N, 2]`` inside
    the action box (as the env takes them); a ValueError naming the field and the fix."""
    from dicrl_torch.solvers.sac.protocol import as_continuous

    demos = as_continuous(demos, spec)  # shapes against the env's (names the fix)
    if demos.action_dim != 2:
        raise ValueError(f"demonstrations field 'actions' has {demos.action_dim} components "
                         f"per agent, but ConstrainedSpread takes a [2] force command per "
                         f"agent; record them with record_demonstrations(ConstrainedSpread"
                         f"(...), ...).")
    box = env.action_space(env.possible_agents[0])
    taken = demos.acting_mask()[..., None]  # [m, T, N, 1]: the actions the env applied
    outside = taken & ((demos.actions < box.low - 1e-6) | (demos.actions > box.high + 1e-6))
    if outside.any():
        k, t, i, c = (int(v) for v in np.argwhere(outside)[0])
        raise ValueError(f"demonstrations field 'actions' holds {demos.actions[k, t, i, c]:.4g} "
                         f"at (episode={k}, time={t}, agent={i}, component={c}), outside the "
                         f"env's action box [{box.low[0]}, {box.high[0]}]; the env clips "
                         f"commands, so store them clipped (np.clip(actions, -1, 1)), as the "
                         f"env took them.")
    return demos


# ------------------------------------------------------------------ the task
class MPETask(SACTask):
    """The constrained MPE spread's run (module docstring): problem, evaluation,
    identifiability, baseline and figures, for the runner
    (:class:`~dicrl_torch.runs.task.Task`).

    Args:
        solver: an untrained :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` whose
            ``env_factory`` builds ``spread_joint_env(constrained, layout=layout,
            **env_kwargs)`` (``absorbing=False``: the game's episodes end at its time
            limit, which is no absorbing state).
        layout: the game's geometry.
        env_kwargs: ConstrainedSpread's other keyword arguments (``max_steps``,
            ``noise_std``, ``local_ratio``), as the solver's env has them.
        split: demonstrations per learner (2-4 learners for D-ICRL; 1 is C-ICRL's).
        seed: seeds the demonstrations, the clones and the evaluation.
        demos: the demonstrations (``ContinuousDemonstrations`` or the path of its
            ``.npz``), or None to record ``sum(split)`` of the via-point experts.
        expert_kwargs: :class:`~dicrl_torch.demos.mpe_experts.ViaPointController` 's keyword
            arguments (``clearance``, ``cruise_speed``, ...).
        true_constraints: ``[l_c]`` bool; None: no ground truth (FPR, FNR and the
            identifiability are ``null``); ``"auto"`` (default): for a
            ``PositionCellBasis`` the cells overlapping the layout's disc and the
            proximity, else the cost basis's own ``true_constraints()`` if it has one,
            else none.
        **settings: :class:`~dicrl_torch.runs.continuous.SACTask` 's (``eval_episodes``,
            ``timesteps``, ``warmup_timesteps``, ``final_*``, ``threshold``,
            ``baseline*``, ...).

    Raises:
        ValueError: the solver's game, the demonstrations or a feature basis do not fit
            the layout (the message names the field and the fix).
    """

    columns = ("FPR", "FNR", "FNR_required", *REGION_COLUMNS, "CVR", "SR")
    game = "mpe_spread"

    def __init__(self, *, solver, layout: SpreadLayout, env_kwargs: Mapping[str, Any]
                 | None = None, split: Sequence[int], seed: int,
                 demos: ContinuousDemonstrations | str | os.PathLike[str] | None = None,
                 expert_kwargs: Mapping[str, Any] | None = None,
                 true_constraints: Any = "auto", **settings: Any) -> None:
        # The settings before the experts' demonstrations, which take seconds.
        self.check_settings(split=split, seed=seed, **settings)
        if not isinstance(layout, SpreadLayout):
            raise ValueError(f"layout must be a SpreadLayout, got {type(layout).__name__}.")
        self.layout = layout
        self.env_kwargs = dict(env_kwargs or {})
        self.expert_kwargs = dict(expert_kwargs or {})
        n = layout.n_agents
        spec = solver.spec
        if spec.state_shape != (n, STATE_DIM):
            raise ValueError(f"The solver's game has joint states {list(spec.state_shape)}, "
                             f"the layout {n} agents of {STATE_DIM} (x, y, vx, vy); build "
                             f"the solver with env_factory=functools.partial("
                             f"spread_joint_env, layout=layout, ...).")
        if solver.absorbing:
            raise ValueError("The solver treats an episode's last state as absorbing, but "
                             "ConstrainedSpread's episodes end at max_steps (truncated), "
                             "not in a goal state: demonstrations would earn a bonus no "
                             "rollout earns. Build the solver with absorbing=False.")
        self._true_env = ConstrainedSpread(layout=layout, constrained=True,
                                           **self.env_kwargs)
        seed = int(seed)
        t0 = time.perf_counter()
        if demos is None:
            demos = self.record_experts(sum(int(m) for m in split), seed)
        elif isinstance(demos, str | os.PathLike):
            demos = load_continuous_demonstrations(demos, n_agents=n, state_dim=STATE_DIM,
                                                   action_dim=2)
        demos = _check_demonstrations(demos, spec, self._true_env)
        self.demos_seconds = time.perf_counter() - t0
        starts = self.start_sample = spread_start_states(layout)
        for role, basis in (("reward_basis", solver.reward_basis),
                            ("cost_basis", solver.cost_basis)):
            # The demonstrations and P0's support: what the learners' statistics read.
            _check_basis(basis, role, demos.states)
            _check_basis(basis, role, starts)
        _check_geometry(solver.reward_basis, solver.cost_basis, layout)
        if isinstance(true_constraints, str) and true_constraints == "auto":
            true_constraints = self._truth(solver.cost_basis)
        super().__init__(solver=solver, demos=demos, split=split, seed=seed,
                         true_constraints=true_constraints, start_states=starts, **settings)
        self._ident: Identifiability | None = None

    def _truth(self, cost_basis: Any) -> np.ndarray | None:
        """The cost features that are true constraints of this layout (class docstring)."""
        lay = self.layout
        if isinstance(cost_basis, PositionCellBasis):
            return cost_basis.true_constraints(
                disc_centre=lay.disc_centre, disc_radius=lay.disc_radius,
                min_distance=lay.min_distance or None).numpy()
        return true_constraints_of(cost_basis)  # a ConstraintBasis's own, or None

    def region_truth(self) -> RegionTruth:
        """The true game's violations as a function of a joint state (every agent
        active): an agent strictly inside the disc, or two agents closer than the
        minimum distance (as ConstrainedSpread checks them); states over the arena,
        velocities up to the agents' top speed."""
        lay = self.layout

        def forbidden(states: np.ndarray) -> np.ndarray:
            pos = states[..., :2]
            disc = in_disc(pos, lay.disc_centre, lay.disc_radius).any(-1)
            return disc | pairwise_too_close(pos, lay.min_distance).any(-1)

        h = lay.arena_half_width
        return RegionTruth(forbidden=forbidden, low=(-h, -h), high=(h, h),
                           max_speed=MAX_SPEED, n_agents=lay.n_agents,
                           kinds=("disc", "proximity"))

    # ------------------------------------------------------------------ experts
    def _env(self, constrained: bool) -> ConstrainedSpread:
        return ConstrainedSpread(layout=self.layout, constrained=constrained,
                                 **self.env_kwargs)

    def expert(self, env: ConstrainedSpread) -> ViaPointController:
        """The experts' controller of ``env``."""
        return ViaPointController(env, **self.expert_kwargs)

    def record_experts(self, n: int, seed: int) -> ContinuousDemonstrations:
        """``n`` successful episodes of the via-point experts in the true game, recorded
        from ``env.state()`` (joint states ``[N, 4]``). Candidates are recorded with
        ``derived_seed(seed, 5)`` and each is kept only if the env, replaying it from its
        seed, reports success without violation; a few spare candidates cover the rare
        failure (e.g. with noise).

        Raises:
            RuntimeError: fewer than ``n`` of the candidates succeed (the message says
                how many, and what to change).
        """
        n = int(n)
        spare = max(2, n // 5)
        env = self._env(constrained=True)
        candidates = record_demonstrations(env, ControllerPolicy(self.expert), n + spare,
                                           derived_seed(seed, 5), use_state=True)
        good = [k for k, s in enumerate(candidates.seeds.tolist())
                if run_episode(env, self.expert(env), seed=int(s)).success]
        if len(good) < n:
            raise RuntimeError(
                f"Only {len(good)} of {n + spare} via-point episodes succeeded without "
                f"violation in this layout (max_steps={env.max_steps}, noise_std="
                f"{env.noise_std}); give the experts time (they settle within about 23 "
                f"steps with 2 agents, 26 with 3), lower the noise, widen their clearance "
                f"(expert_kwargs) or ask for fewer demonstrations.")
        return candidates.subset(good[:n])

    def _fly(self, make: Callable[[ConstrainedSpread], Any], seeds: Sequence[int],
             constrained: bool) -> list:
        """Episodes of the controller ``make(env)`` from the given reset seeds."""
        env = self._env(constrained)
        return [run_episode(env, make(env), seed=int(s)) for s in seeds]

    def evaluation_seeds(self) -> np.ndarray:
        """``[eval_episodes]`` the reset seeds of the learners' evaluation rollouts (as
        the solver draws them from :meth:`evaluation_rng`), for the reference rows."""
        return self.evaluation_rng().integers(0, 2**31 - 1, size=self.eval_episodes)

    def reference_rows(self) -> dict[str, dict]:
        """The experts (via-point) and the nominal controller (straight to the
        landmarks), flown in the TRUE game from the learners' evaluation starts."""
        rows = {}
        seeds = self.evaluation_seeds()
        for name, make in (("Experts (ground truth)", self.expert),
                           ("Experts (nominal)", NominalController)):
            episodes = self._fly(make, seeds, constrained=True)
            rows[name] = {"CR_mean": None, "CR_std": None, "RFD": None, "FPR": None,
                          "FNR": None, "FNR_required": None,
                          "SR": float(np.mean([e.success for e in episodes])),
                          "CVR": float(np.mean([e.violated.mean() for e in episodes]))}
        return rows

    # ------------------------------------------------------------------ rows
    def describe(self) -> str:
        truth = "no ground truth" if self.true is None \
            else f"{int(self.true.sum())} of them true constraints"
        return (f"constrained MPE spread, {self.layout.n_agents} agents; "
                f"{len(self.split)} learners holding {self.split} demonstrations; "
                f"{self.cost_basis.dim} cost features, {truth}")

    def warmup_summary(self, solution) -> str:
        return (f"{solution.violation_rate:.2f} of the agents cross a true constraint; "
                f"μ_r = {[round(float(x), 2) for x in solution.mu_r]}")

    def evaluate_policy(self, solver, deterministic: bool) -> tuple[float, float, list]:
        """SR and CVR (module docstring) of ``solver``'s policy in the TRUE game, and the
        rollouts' positions ``[L+1, N, 2]``."""
        ev = solver.evaluate(self.eval_episodes, deterministic=deterministic,
                             true_game=True, trajectories=True, rng=self.evaluation_rng())
        violated = ev.violated.numpy()
        final = np.stack([p[-1, :, :2] for p in ev.paths])
        success = spread_success(final, violated, self.layout)
        return (float(success.mean()), float(violated.mean()),
                [p[:, :, :2] for p in ev.paths])

    def constraint_map(self, label: str, row: dict, rollouts: Rollouts = ()) -> np.ndarray:
        """The learned constraint cells (hatched) and up to 9 of the row's ``rollouts``
        (positions ``[L+1, N, 2]``, :meth:`evaluate_policy`'s; none for a row taken from
        a checkpoint)."""
        mask = self.learned_mask(row)
        paths = list(rollouts)[:9]
        return render_spread(
            self.layout, cells=self._cells(mask), trajectories=paths,
            title=self._title(f"{label}: learned constraints (hatched)", mask))

    def _title(self, title: str, mask: np.ndarray) -> str:
        """``title``, plus a line naming the features of ``mask`` a map shows no cell
        of (e.g. the proximity)."""
        n_cells = len(self._rectangles())  # the cell features come first
        extra = [self.cost_basis.names[j] for j in np.flatnonzero(mask) if j >= n_cells]
        return title + ("\n+ " + ", ".join(extra) if extra else "")

    def _rectangles(self) -> np.ndarray:
        """``[C, 4]`` the cost basis's cells ``(x0, y0, x1, y1)``, its first ``C``
        features (``[0, 4]`` for a basis without cells, or not a ContinuousFeatureBasis)."""
        if not isinstance(self.cost_basis, ContinuousFeatureBasis):
            return np.zeros((0, 4))
        return np.asarray(self.cost_basis.cell_rectangles())

    def _cells(self, mask: np.ndarray) -> np.ndarray:
        """``[K, 4]`` rectangles of the cell features in ``mask`` ``[l_c]`` bool."""
        r = self._rectangles()
        return r[np.asarray(mask[:len(r)], dtype=bool)]

    # ------------------------------------------------------------------ identifiability
    def identifiability(self) -> Identifiability | None:
        """The true constraint features by class (module docstring, step 4); None
        without a ground truth. Computed once."""
        if self.true is None:
            return None
        if self._ident is not None:
            return self._ident
        t0 = time.perf_counter()
        basis = self.cost_basis
        demos = self.demos
        with torch.no_grad():
            phi = basis(torch.from_numpy(np.array(demos.states[:, 1:]))).numpy()
        steps = demos.step_mask()[..., None]  # [m, T, 1]: the next states s_1..s_L
        accrued = ((phi > 0) & steps).any((0, 1))
        with torch.no_grad():
            accrued |= (basis(torch.from_numpy(self.start_sample)) > 0).any(0).numpy()
        # The nominal controller from the demonstrations' own starts (their seeds), or
        # from fresh ones for demonstrations without seeds.
        seeds = demos.seeds if demos.seeds is not None else np.random.default_rng(
            derived_seed(self.seed, 6)).integers(0, 2**31 - 1, size=demos.n_episodes)
        episodes = self._fly(NominalController, seeds.tolist(), constrained=False)
        with torch.no_grad():
            used = np.stack([(basis(torch.from_numpy(e.states[1:])) > 0).any(0).numpy()
                             for e in episodes])  # [n, l]
        true = torch.from_numpy(self.true)
        acc, share = torch.from_numpy(accrued), torch.from_numpy(used.mean(0))
        demonstrated = true & acc
        required = true & ~acc & (share > 0)
        self._ident = Identifiability(
            names=list(basis.names), scope=true.clone(), demonstrated=demonstrated,
            required=required, undetermined=true & ~acc & (share == 0),
            probability=torch.where(true & ~acc, share.double(), torch.nan),
            infeasible=torch.zeros_like(true), min_probability=1.0 / len(episodes),
            temperature=0.0, seconds=time.perf_counter() - t0, n_solves=0, accrued=acc)
        return self._ident

    def annotate(self, methods: dict) -> dict | None:
        """Adds to every learned row ``FNR_required``, the true set's class counts and
        ``contradictions`` (learned constraints the demonstrations or P0 accrue);
        returns ``results.json``'s ``identifiability`` record (``probability``: the
        share of nominal rollouts that accrue the feature; None without a truth)."""
        ident = self.identifiability()
        for m in methods.values():
            for row in m["learners"]:
                if "constraints" not in row:  # reference rows learn nothing
                    continue
                if ident is None:
                    row.update(dict.fromkeys(ANNOTATIONS))
                    continue
                learned = torch.from_numpy(self.learned_mask(row))
                row.update(FNR_required=fnr_required(learned, torch.from_numpy(self.true),
                                                     ident),
                           n_demonstrated=ident.n_demonstrated, n_required=ident.n_required,
                           n_undetermined=ident.n_undetermined,
                           contradictions=ident.names_of(learned & ident.accrued))
        return None if ident is None else ident.as_dict()

    # ------------------------------------------------------------------ figures
    def figures(self, *, methods: dict, histories: dict, experiment: str,
                eval_every: int) -> dict[str, np.ndarray]:
        """The demonstrations and the true constraint cells; the cost weights' curves."""
        true = self.true if self.true is not None else np.zeros(self.cost_basis.dim, bool)
        paths = [s[:int(n) + 1, :, :2] for s, n in zip(self.demos.states, self.demos.lengths,
                                                         strict=True)]
        images = super().figures(methods=methods, histories=histories,
                                 experiment=experiment, eval_every=eval_every)
        images["spread_demonstrations"] = render_spread(
            self.layout, cells=self._cells(true), trajectories=paths,
            title=self._title(f"{experiment}: {self.demos.n_episodes} demonstrations and "
                              f"the true constraints (hatched)", true))
        return images


# ------------------------------------------------------------------ builder
def build_mpe_task(
    *, layout: SpreadLayout | Mapping[str, Any] | None = None,
    env: Mapping[str, Any] | None = None, reward_basis: Any = None, cost_basis: Any = None,
    solver: Callable[..., Any] | Mapping[str, Any] | None = None, split: Sequence[int] =
    (10, 10), seed: int = 0, demos: Any = None, expert: Mapping[str, Any] | None = None,
    **settings: Any,
) -> MPETask:
    """The constrained spread's :class:`MPETask` from plain keyword arguments.

    Args:
        layout: a :class:`~dicrl_torch.envs.mpe.SpreadLayout` or its keyword arguments
            (default: 2 agents).
        env: ConstrainedSpread's other keyword arguments (``max_steps``, ``noise_std``,
            ``local_ratio``; default ``{}``: 50 steps, no noise).
        reward_basis: default ``LandmarkRewardBasis(n_agents=N, landmarks=...)``
            (coverage of each landmark, ``l_r = N``).
        cost_basis: default ``PositionCellBasis`` of 8 x 8 cells over the arena plus the
            proximity (``l_c = 65``; 5 true constraints: the 4 cells under the disc and
            the proximity).
        solver: the :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` class or a
            ``functools.partial`` of it (e.g. Hydra's ``_partial_``), or a dict of its
            keyword arguments, or None for the defaults below; ``env_factory``,
            ``reward_basis``, ``cost_basis`` and ``seed`` (``derived_seed(seed, 1)``) are
            supplied here. Defaults: ``absorbing=False``, ``ent_coef=0.1``, ``n_envs=4``,
            ``learning_rate=1e-3``, ``scale_observations=True``.
        split, seed, demos: as :class:`MPETask`.
        expert: ViaPointController's keyword arguments.
        **settings: the rest of :class:`MPETask` 's (``eval_episodes``, ``timesteps``,
            ``warmup_timesteps``, ...).
    """
    from dicrl_torch.solvers.sac import SACConstrainedSolver

    if layout is None or isinstance(layout, Mapping):
        layout = SpreadLayout(**dict(layout or {}))
    env_kwargs = dict(env or {})
    for key in ("layout", "constrained"):
        if key in env_kwargs:
            raise ValueError(f"env must not set {key!r}: pass the layout as layout=..., and "
                             f"the solver sets constrained.")
    n = layout.n_agents
    if reward_basis is None:
        reward_basis = LandmarkRewardBasis(n_agents=n, landmarks=layout.landmarks,
                                           state_dim=STATE_DIM)
    if cost_basis is None:
        h = layout.arena_half_width
        cost_basis = PositionCellBasis(
            n_agents=n, bounds=((-h, h), (-h, h)), n_per_axis=8, state_dim=STATE_DIM,
            proximity_radius=layout.min_distance or 1e-9, obstacle_centre=layout.disc_centre,
            obstacle_radius=layout.disc_radius, min_distance=layout.min_distance)
    defaults = dict(absorbing=False, ent_coef=0.1, n_envs=4, learning_rate=1e-3,
                    scale_observations=True)
    if solver is None or isinstance(solver, Mapping):
        make, options = SACConstrainedSolver, {**defaults, **dict(solver or {})}
    elif callable(solver):
        make, options = solver, {}
    else:
        raise ValueError(f"solver must be None, a dict of SACConstrainedSolver's keyword "
                         f"arguments or a callable building one, got "
                         f"{type(solver).__name__}.")
    built = make(env_factory=functools.partial(spread_joint_env, layout=layout, **env_kwargs),
                 reward_basis=reward_basis, cost_basis=cost_basis,
                 seed=derived_seed(int(seed), 1), **options)
    return MPETask(solver=built, layout=layout, env_kwargs=env_kwargs, split=split,
                   seed=seed, demos=demos, expert_kwargs=expert, **settings)
