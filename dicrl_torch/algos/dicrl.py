"""D-ICRL: the distributed bi-level learner (paper Algorithms 1–2, docs/design.md §5).

Every learner ``v`` holds ``ω_c^[v] ∈ [0, 1]^d``, a gradient tracker and, for each
learner ``u``'s inner process, its own copy ``η^[v](ω_c^[u]) = [ω_r, λ]``. State is
stacked along a leading axis of the learners local to this process (all of them in
the simulated backend, one per process under torch.distributed); the communicator
mixes it. C-ICRL is this trainer with one learner holding all demonstrations.

Inner process (Algorithm 2) for a cost vector ω_c, over k = 0..K-2::

    η^[v](k+1) = Σ_v' W(k)[v,v'] η^[v'](k) − α(k) m^[v] ∇G^[v](η^[v](k); ω_c)
    η̄^[v] = Σ_k α(k) η^[v](k) / Σ_k α(k),        α(k) = ᾱ / (k + 1)

Outer step (Algorithm 1) for learner v::

    g^[v](n)  = LGA at (ω_c^[v](n), η̄^[v])                   (dicrl_torch.algos.icrl)
    y^[v](n)  = Σ_v' W̄[v,v'] y^[v'](n−1) + g^[v](n) − g^[v](n−1)     (y(0) = g(0))
    ω̃^[v]    = Proj_[0,1](ω_c^[v] + N_L y^[v] / ρ)              (LSCA; the paper: ρ = 1)
    ω_c^[v](n+1) = Σ_v' W̄[v,v'] (ω_c^[v'] + β(n)(ω̃^[v'] − ω_c^[v']))

Beyond the paper, two inner methods track the network-average gradient
(:mod:`dicrl_torch.algos.inner`): ``"tracking"`` keeps Algorithm 2's steps and average and
makes the network take C-ICRL's step; ``"gradient_tracking"`` takes a constant step.

Departures from the paper, each optional and documented in the config: the LSCA
curvature ρ (the printed step ``ω_c + N_L y`` moves by the raw likelihood gradient,
whose scale grows with m and |λ|); warm starts of η across outer iterations; and
``prune_accrued``: with budget b = 0 a feature that a learner's own demonstrations
accrue cannot be a constraint, so that learner projects it to 0.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from dicrl_torch.algos.callbacks import TrainerCallback
from dicrl_torch.algos.icrl import dual_gradient, local_gradient
from dicrl_torch.algos.inner import InnerProcesses
from dicrl_torch.algos.models import LearnerModel, ModelSolution, TabularLearnerModel
from dicrl_torch.checks import setting_bool, setting_choice, setting_int, setting_number
from dicrl_torch.comm.communicator import fixed_order_mix
from dicrl_torch.comm.graphs import (
    MixingSchedule,
    check_inner_schedule,
    check_outer_schedule,
    strongly_connected,
)
from dicrl_torch.features.bases import FeatureBasis
from dicrl_torch.metrics import learned_constraints
from dicrl_torch.solvers.factored import FactoredSoftBellman

Schedule = MixingSchedule
# Bits of a feature mask packed into one float64 word: every integer below 2**53 is exact.
_MASK_BITS = 52


class NonFiniteError(FloatingPointError):
    """A NaN or inf appeared in a learner's parameters or gradients.

    The message names the quantity, the outer iteration, the inner step (if any) and
    the learner; the run stops there, so no checkpoint ever holds the bad values.
    """


@dataclass(frozen=True)
class StepSizes:
    """``α(k) = alpha_bar / (k + 1)`` (inner) and ``β(n) = beta_bar / (n + 1)^beta_power``
    (outer; ``Σβ = ∞`` and ``Σβ² < ∞`` need ``beta_power ∈ (1/2, 1]``).

    ``multiplier_scale`` multiplies the λ coordinate of every inner step: a constant
    diagonal preconditioner, i.e. the same gradient method on ``λ / sqrt(scale)``. It
    matters when ``μ_r`` and ``J_ωc`` live on very different scales (the drones: μ_r is
    tens per feature, J a few units), where one α either overshoots ω_r or starves λ.
    """

    alpha_bar: float = 0.05
    beta_bar: float = 0.5
    beta_power: float = 0.6
    multiplier_scale: float = 1.0

    def __post_init__(self) -> None:
        setting_number("alpha_bar", self.alpha_bar, low=0, low_open=True, example=0.02,
                       why="α(k) = ᾱ/(k+1)")
        setting_number("multiplier_scale", self.multiplier_scale, low=0, low_open=True,
                       example=1.0, why="the λ coordinate's step is scaled by it; 1: the "
                                        "paper's")
        setting_number("beta_bar", self.beta_bar, low=0, high=1, low_open=True,
                       high_open=True, example=0.5, why="so that β(n) ∈ (0, 1), Theorem 1")
        setting_number("beta_power", self.beta_power, low=0.5, high=1, low_open=True,
                       example=0.6, why="so that Σβ = ∞ and Σβ² < ∞, Theorem 1")

    def alpha(self, k: int) -> float:
        return self.alpha_bar / (k + 1)

    def beta(self, n: int) -> float:
        return self.beta_bar / (n + 1) ** self.beta_power


_OPTION_RULES: dict[str, Callable[[Any], Any]] = {
    "inner_steps": lambda v: setting_int("inner_steps", v, least=2, example=6,
                                         why="K: Algorithm 2 takes K - 1 steps"),
    "lsca_curvature": lambda v: setting_number("lsca_curvature", v, low=0, low_open=True,
                                               example=300.0, why="ρ of the LSCA step"),
    "prune_accrued": lambda v: setting_bool("prune_accrued", v),
    "merge_stateful_inner": lambda v: setting_bool("merge_stateful_inner", v),
    "inner_method": lambda v: setting_choice("inner_method", v,
                                             ("paper", "tracking", "gradient_tracking")),
    "inner_step": lambda v: setting_number(
        "inner_step", v, low=0, low_open=True, example=0.005,
        why="the constant step of inner_method=gradient_tracking"),
    "init_cost_weights": lambda v: setting_number("init_cost_weights", v, low=0, high=1,
                                                  example=0.0, why="ω_c(0) lives in [0, 1]^d"),
    "init_reward_weights": lambda v: setting_number("init_reward_weights", v, example=0.0),
    "init_multiplier": lambda v: setting_number("init_multiplier", v, example=-1.0,
                                                why="λ(0)"),
}
# Initial weights may also be arrays (one value per learner and feature): DICRL checks
# those itself, with their shapes.
_ARRAY_OPTIONS = ("init_cost_weights", "init_reward_weights")


def check_trainer_options(**options: Any) -> None:
    """Refuse :class:`DICRL`'s scalar options out of range, naming the first (those given;
    others are ignored). :class:`DICRL` checks its own; a trainer's settings built before
    any run (:class:`~dicrl_torch.runs.runner.TrainerSpec`) check theirs with it.

    Raises:
        InvalidSetting: naming the option, what it must be and an example.
    """
    for name, rule in _OPTION_RULES.items():
        if name in options and not (name in _ARRAY_OPTIONS
                                    and hasattr(options[name], "shape")):
            rule(options[name])


@dataclass
class LearnerState:
    """Everything a learner carries between outer iterations (for checkpoints).

    Attributes (leading axis: local learners):
        cost_weights: ``[n, d]`` ω_c.
        eta: ``[N_L, n, p]`` warm-start η for each inner process u (p = l_r + 1).
        eta_bar: ``[n, p]`` the averaged η̄ of each learner's own inner process.
        tracker, last_lga: ``[n, d]`` y(n−1) and g(n−1).
        groups: inner processes known to coincide (see ``_inner_groups``).
    """

    cost_weights: torch.Tensor
    eta: torch.Tensor
    eta_bar: torch.Tensor
    tracker: torch.Tensor | None = None
    last_lga: torch.Tensor | None = None
    outer_iteration: int = 0
    groups: list[list[int]] = field(default_factory=list)


class DICRL(InnerProcesses):
    """The D-ICRL trainer.

    Args:
        learner_model: the learners' model of the experts (bases + inner solver, see
            :mod:`dicrl_torch.algos.models`), e.g. the drones' ``SACLearnerModel``.
        solver, reward_basis, cost_basis: shorthand for
            ``learner_model=TabularLearnerModel(solver=..., reward_basis=...,
            cost_basis=...)`` (the grid world); give these or ``learner_model``.
        shards: demonstrations of the local learners, in ``communicator.local_ids`` order
            (whatever the learner model reads: grid ``Demonstrations``, drone pairs).
        trajectory_counts: ``m^[v]`` of *every* learner (public: it scales the steps).
        communicator: mixes η, ω_c and trackers between learners.
        inner_schedule, outer_schedule: ``k -> W(k)`` and ``n -> W̄(n)`` ``[N_L, N_L]``.
        steps: step-size schedules.
        inner_steps: K, inner iterations per outer iteration (>= 2).
        lsca_curvature: ρ of the LSCA surrogate (1 in the paper).
        prune_accrued: zero features the learner's own demonstrations accrue.
        merge_identical_inner: run one inner process for learners with equal ω_c and a
            shared warm start (one problem): bit-identical for a stateless model (tested).
        merge_stateful_inner: merge those of a stateful model (SAC) too. Unmerged, each
            learner's solver trains through all N_L processes (N_L (K - 1) solves per
            outer iteration, where C-ICRL takes K - 1): merged, fewer updates, other
            numbers.
        inner_method: ``"paper"`` (Algorithm 2, the default here), ``"tracking"`` (the
            configs' default: Algorithm 2's steps on a tracked average gradient) or
            ``"gradient_tracking"`` (constant ``inner_step``): :mod:`~.inner`.
        callbacks: :class:`~dicrl_torch.algos.callbacks.TrainerCallback` s called during
            :meth:`train` (logging, checkpoints, evaluation, stopping), before those
            given to :meth:`train` itself.
        init_cost_weights: ``[N_L, d]`` or a scalar; init_reward_weights ``[l_r]`` or
            scalar; init_multiplier λ(0).

    Raises:
        InvalidSetting: an option out of range (:func:`check_trainer_options`), checked
            before anything else.
        ValueError: shards, counts or schedules that do not fit the communicator.
    """

    def __init__(self, *, learner_model: LearnerModel | None = None,
                 solver: FactoredSoftBellman | None = None,
                 reward_basis: FeatureBasis | None = None,
                 cost_basis: FeatureBasis | None = None, shards: Sequence,
                 trajectory_counts: Sequence[int], communicator, inner_schedule: Schedule,
                 outer_schedule: Schedule, steps: StepSizes = StepSizes(),
                 inner_steps: int = 10, lsca_curvature: float = 1.0,
                 prune_accrued: bool = False,
                 init_cost_weights: float | torch.Tensor = 0.5,
                 init_reward_weights: float | torch.Tensor = 0.0,
                 init_multiplier: float = -1.0, progress: bool = False,
                 merge_identical_inner: bool = True, merge_stateful_inner: bool = False,
                 inner_method: str = "paper", inner_step: float = 0.01,
                 callbacks: Sequence[TrainerCallback] = ()) -> None:
        check_trainer_options(
            inner_steps=inner_steps, lsca_curvature=lsca_curvature,
            prune_accrued=prune_accrued, inner_method=inner_method, inner_step=inner_step,
            merge_stateful_inner=merge_stateful_inner,
            init_cost_weights=init_cost_weights, init_reward_weights=init_reward_weights,
            init_multiplier=init_multiplier)
        self.comm = communicator
        N_L = communicator.n_learners
        local = communicator.local_ids
        if learner_model is None:
            if solver is None or reward_basis is None or cost_basis is None:
                raise ValueError("Give learner_model, or solver, reward_basis and cost_basis "
                                 "(the tabular grid-world model).")
            learner_model = TabularLearnerModel(solver=solver, reward_basis=reward_basis,
                                                cost_basis=cost_basis)
        elif solver is not None or reward_basis is not None or cost_basis is not None:
            raise ValueError("Give either learner_model or solver/reward_basis/cost_basis, "
                             "not both.")
        self.learner_model = learner_model
        if len(shards) != len(local):
            raise ValueError(f"{len(shards)} demonstration shards for {len(local)} local "
                             f"learners {local}; give one shard per local learner.")
        if len(trajectory_counts) != N_L:
            raise ValueError(f"trajectory_counts lists {len(trajectory_counts)} learners, "
                             f"the communicator has {N_L}.")
        self.stats = [learner_model.statistics(s) for s in shards]
        for v, st in zip(local, self.stats, strict=True):
            if st.m != trajectory_counts[v]:
                raise ValueError(f"Learner {v} holds {st.m} trajectories but "
                                 f"trajectory_counts says {trajectory_counts[v]}; the shard "
                                 f"partition and the counts must agree.")
        # Assumptions 1-3 are checked before any computation.
        check_inner_schedule(inner_schedule, horizon=max(100, inner_steps))
        check_outer_schedule(outer_schedule)
        self.inner_method, self.inner_step = inner_method, float(inner_step)
        self.callbacks = list(callbacks)
        self._active: list[TrainerCallback] = []  # during train(): these and its own
        self._log_rows: list[int] = []  # local learners whose own inner process runs now
        self._process = 0  # the learner whose ω_c the running inner process is for
        self.shards = list(shards)
        self.m = torch.tensor([float(trajectory_counts[v]) for v in local], dtype=torch.float64)
        self.inner_schedule, self.outer_schedule = inner_schedule, outer_schedule
        self.steps, self.K = steps, inner_steps
        self.rho, self.prune_accrued = float(lsca_curvature), prune_accrued
        self.progress = progress
        stateful = getattr(learner_model, "stateful", False)
        self.merge = merge_identical_inner and (merge_stateful_inner or not stateful)
        # A stateful model's merged run trains other policies: not resumable as unmerged.
        self._merged_stateful = bool(stateful and self.merge)
        self.n_learners, self.local = N_L, local
        d, lr = learner_model.cost_dim, learner_model.reward_dim
        self.accrued = torch.stack([s.cost_accrual > 0 for s in self.stats])  # [n, d]
        # Features P0 gives mass to: with budget 0 none can be a constraint. Every learner
        # knows P0, so they are held at 0 from ω_c(0) on (and stay 0 through consensus).
        self.pinned = learner_model.start_features().to(torch.bool)  # [d]
        if bool(self.pinned.all()):
            warnings.warn("Every cost feature is positive on the start states (P0), so with "
                          "budget 0 none can be a constraint and ω_c stays 0; use a basis of "
                          "indicators (e.g. cells) to learn constraints.", stacklevel=2)

        cw = torch.as_tensor(init_cost_weights, dtype=torch.float64)
        cw = cw.expand(N_L, d).clone() if cw.dim() == 0 else cw.clone()
        if cw.shape != (N_L, d) or not ((cw >= 0) & (cw <= 1)).all():  # NaN fails too
            raise ValueError(f"init_cost_weights must be a scalar or [{N_L}, {d}] in [0, 1].")
        cw[:, self.pinned] = 0.0
        rw = torch.as_tensor(init_reward_weights, dtype=torch.float64).expand(lr).clone()
        if not torch.isfinite(rw).all():
            raise ValueError(f"init_reward_weights must be finite, got {init_reward_weights}; "
                             f"give a finite number (0.0 is the default).")
        eta0 = torch.cat([rw, torch.tensor([float(init_multiplier)], dtype=torch.float64)])
        n = len(local)
        self.state = LearnerState(
            cost_weights=cw[local].clone(),
            eta=eta0.expand(N_L, n, lr + 1).clone(),
            eta_bar=eta0.expand(n, lr + 1).clone(),
        )
        self._cost_all = cw  # ω_c of every learner, as last gathered
        self.history: list[dict] = []
        self.solves = 0
        seed_copies = getattr(communicator, "seed_copies", None)
        if callable(seed_copies):  # the initial values are public
            seed_copies("eta", eta0.expand(N_L, lr + 1))
            for field_name in ("cost_weights", "lsca_target"):
                seed_copies(field_name, cw)

    # ------------------------------------------------------------------ numerical guard
    def _check_finite(self, what: str, values: torch.Tensor, inner_step: int | None = None,
                      process: int | None = None) -> None:
        """Raise :class:`NonFiniteError` if a row of ``values`` ``[n_local, ...]`` holds a
        NaN or inf.

        Checked right after each value is computed and before it is sent, so the learner
        named is the one where the problem arose, not a neighbour it spread to.

        Args:
            what: the quantity, as the message names it.
            values: one row per local learner.
            inner_step: k within the inner process, or None for outer quantities.
            process: the learner whose ω_c the inner process is for.
        """
        ok = torch.isfinite(values.reshape(values.shape[0], -1)).all(1)
        if bool(ok.all()):
            return
        i = int((~ok).nonzero()[0])
        where = f"outer iteration {self.state.outer_iteration}"
        if inner_step is not None:
            where += f", inner step {inner_step}"
            if process is not None and process != self.local[i]:
                where += f" (the inner process for learner {process}'s ω_c)"
        hint = ("Lower the step sizes (algo.steps.alpha_bar, algo.inner_step, "
                "algo.steps.beta_bar) or raise algo.lsca_curvature, and solve in float64 "
                "(solver.dtype=float64)")
        if getattr(self.learner_model, "dtype", None) == torch.float32:
            hint += ("; the solver computes in float32, which overflows beyond ~3.4e38 and "
                     "loses the policy's accuracy from |V| ~ 1e7 on")
        raise NonFiniteError(
            f"{what} of learner {self.local[i]} is not finite (NaN or inf) at {where}: "
            f"{values[i].flatten()[:8].tolist()}. {hint}.")

    # ------------------------------------------------------------------ model pieces
    def solve(self, i: int, eta: torch.Tensor, cost_weights: torch.Tensor) -> ModelSolution:
        """Local learner ``i``'s policy for ``η`` ``[p]`` and ``ω_c`` ``[d]``."""
        self.solves += 1
        return self.learner_model.solve(i, eta, cost_weights)

    def solve_all(self, eta: torch.Tensor, cost_weights: torch.Tensor) -> list[ModelSolution]:
        """Every local learner's policy, learner ``i`` for ``η`` ``eta[i]`` and ``ω_c``
        ``cost_weights[i]``; through the model's ``solve_all`` where it has one (its
        learners solved together, the same numbers)."""
        solve_all = getattr(self.learner_model, "solve_all", None)
        if not callable(solve_all):
            return [self.solve(i, eta[i], cost_weights[i]) for i in range(len(eta))]
        self.solves += len(eta)
        return solve_all(eta, cost_weights)

    # ------------------------------------------------------------------ inner process
    def _scaled_gradients(self, eta: torch.Tensor, cost_weights: torch.Tensor,
                          k: int, stats: list | None = None,
                          m: torch.Tensor | None = None) -> torch.Tensor:
        """``m^[v] ∇G^[v](η^[v]; ω_c)`` of every local learner: ``[n, p]``; ``cost_weights``
        ``[d]`` (the running process's) or ``[n, d]`` (each learner's own); ``stats`` and
        ``m`` ``[n]``: other demonstrations' statistics and counts than the learners'."""
        stats = self.stats if stats is None else stats
        m = self.m if m is None else m
        cost_all = cost_weights.expand(len(stats), -1)
        solutions = self.solve_all(eta, cost_all)
        grads = torch.stack([dual_gradient(sol, st, w) for sol, st, w
                             in zip(solutions, stats, cost_all, strict=True)])
        for cb in self._active:
            cb.on_inner_gradients(self, learners=self._log_rows,
                                  step=self.state.outer_iteration * self.K + k,
                                  gradients=grads, eta=eta)
        scaled = m[:, None] * grads
        scaled[:, -1] *= self.steps.multiplier_scale
        return scaled

    def _inner_matrix(self, k: int) -> torch.Tensor:
        """W(k) of the running inner process; over failing links (``comm.link_failure``)
        the round's realised graph, the same on every learner, its support added to the
        process's union (Assumption 1 is checked on it)."""
        W = self.inner_schedule(k)
        failures = getattr(self.comm, "link_failures", None)
        if failures is None:
            return W
        W = failures.realise(W, self.state.outer_iteration, self._process, k)
        self._union = (W > 0) if k == 0 else self._union | (W > 0)
        return W

    def _inner_groups(self, cost_all: torch.Tensor, previous: list[list[int]]) -> list[list[int]]:
        """Learners whose inner processes solve one problem: equal ω_c and warm-started
        from one shared process (or all from the initial η). Decided from globally known
        values only, so every process of a distributed run agrees."""
        n = self.state.outer_iteration
        owner = {u: i for i, g in enumerate(previous) for u in g} if n > 0 else {}
        groups: list[list[int]] = []
        for u in range(self.n_learners):
            for g in groups:
                r = g[0]
                same_prev = n == 0 or owner.get(u) == owner.get(r)
                if self.merge and same_prev and torch.equal(cost_all[u], cost_all[r]):
                    g.append(u)
                    break
            else:
                groups.append([u])
        return groups

    # ------------------------------------------------------------------ outer iteration
    def _cost_weights_equal(self) -> bool:
        """Whether every learner's ω_c is known, from public values alone, to be equal bit
        for bit: the initial ω_c when equal, and the ω_c after a W̄(n) whose rows are all
        equal (every learner then computes the same sum)."""
        n = self.state.outer_iteration
        if n == 0:
            return bool((self._cost_all == self._cost_all[0]).all())
        return bool((self.outer_schedule(n - 1) == self.outer_schedule(n - 1)[0]).all())

    def _cost_weights_of_all(self) -> torch.Tensor:
        """Every learner's ω_c ``[N_L, d]``: gathered, or (``skip_redundant_rounds``) known
        without a round where they are equal."""
        st = self.state
        if getattr(self.comm, "skip_redundant_rounds", False) and self._cost_weights_equal():
            return st.cost_weights[:1].expand(self.n_learners, -1).clone()
        return self.comm.all_gather(st.cost_weights, "cost_weights")

    def _mix_cost_weights(self, target: torch.Tensor, W_bar: torch.Tensor) -> torch.Tensor:
        """ω_c(n + 1) ``[n_local, d]`` = Σ_v' W̄[v, v'] (ω_c + β(n) (ω̃^[v'] − ω_c)).

        With compressed messages and every ω_c known equal, the learners send their LSCA
        targets ω̃ and each receiver completes the half step: a target stuck at a bound
        is the same from one iteration to the next, so a delta message skips it, where the
        half step moves every entry whose ω_c still moves. The half steps are computed
        with the same operations as the sender's, so lossless messages give the paper's
        numbers bit for bit. Mixed without the residual, compressed ω_c stay equal
        wherever W̄'s rows are."""
        st, beta = self.state, self.steps.beta(self.state.outer_iteration)
        if getattr(self.comm, "compression", None) is not None and self._cost_weights_equal():
            targets = self.comm.exchange(target, "lsca_target")  # [N_L, d]
            cw = st.cost_weights[0]
            half = cw + beta * (targets - cw)
            self._check_finite("ω_c", half[self.local])
            return fixed_order_mix(half, W_bar, self.local)
        half = st.cost_weights + beta * (target - st.cost_weights)
        self._check_finite("ω_c", half)
        return self.comm.mix(half, W_bar, "cost_weights", keep_residual=False)

    def outer_step(self) -> dict:
        """One iteration of Algorithm 1 for every local learner; returns diagnostics."""
        st, n = self.state, self.state.outer_iteration
        t0 = time.perf_counter()
        cost_all = self._cost_weights_of_all()  # [N_L, d]
        groups = self._inner_groups(cost_all, st.groups)
        new_eta = torch.empty_like(st.eta)
        eta_bar_own = torch.empty_like(st.eta_bar)
        disconnected = 0
        for g in groups:
            self._log_rows = [i for i, v in enumerate(self.local) if v in g]
            self._process = g[0]
            bar, last = self.inner_process(cost_all[g[0]], st.eta[g[0]])
            if getattr(self.comm, "link_failures", None) is not None:
                disconnected += not strongly_connected(self._union.numpy())
            for u in g:
                new_eta[u] = last
                for i, v in enumerate(self.local):
                    if v == u:
                        eta_bar_own[i] = bar[i]
        self._check_finite("The averaged η̄", eta_bar_own)
        st.eta, st.eta_bar, st.groups = new_eta, eta_bar_own, groups

        # Local gradient approximation at each learner's own (ω_c, η̄).
        lga = torch.stack([
            local_gradient(sol, self.stats[i], float(st.eta_bar[i, -1]))
            for i, sol in enumerate(self.solve_all(st.eta_bar, st.cost_weights))])
        self._check_finite("The local gradient (LGA)", lga)
        W_bar = self.outer_schedule(n)
        if st.tracker is None:
            tracker = lga
        else:
            tracker = self.comm.mix(st.tracker, W_bar, "tracker") + lga - st.last_lga
        self._check_finite("The gradient tracker y", tracker)
        target = (st.cost_weights + self.n_learners * tracker / self.rho).clamp(0.0, 1.0)
        if self.prune_accrued:
            target = torch.where(self.accrued, 0.0, target)
        target = torch.where(self.pinned, 0.0, target)
        st.cost_weights = self._mix_cost_weights(target, W_bar)
        st.tracker, st.last_lga = tracker, lga
        st.outer_iteration = n + 1
        info = {
            "outer_iteration": n,
            "inner_processes": len(groups),
            "seconds": time.perf_counter() - t0,
            "multiplier": st.eta_bar[:, -1].tolist(),
            "lga_norm": lga.norm(dim=1).tolist(),
            # [L][d]: each local learner's ω_c after the step (figures.cost_weight_curves)
            "cost_weights": st.cost_weights.tolist(),
            # [L]: the algorithm's bytes each local learner has sent so far
            "bytes_sent": [self.comm.traffic.bytes_sent(v) for v in self.local],
        }
        if getattr(self.comm, "link_failures", None) is not None:
            # inner processes whose rounds together did not connect the learners
            info["disconnected_inner_processes"] = disconnected
        self.history.append(info)
        return info

    def train(self, outer_iterations: int,
              callbacks: Sequence[TrainerCallback] = ()) -> LearnerState:
        """Run outer iterations until ``outer_iterations`` in total (a resumed trainer
        continues where its checkpoint stopped), with a progress bar.

        Args:
            callbacks: called after the trainer's own ``callbacks``.
        """
        self._active = [*self.callbacks, *callbacks]
        try:
            return self._train(outer_iterations)
        finally:
            self._active = []

    def _train(self, outer_iterations: int) -> LearnerState:
        if outer_iterations < 1:
            raise ValueError(f"outer_iterations must be >= 1, got {outer_iterations}.")
        start = self.state.outer_iteration
        if start >= outer_iterations:
            return self.state
        it = range(start, outer_iterations)
        bar = None
        if self.progress:
            from tqdm.auto import tqdm
            bar = tqdm(it, desc=f"D-ICRL x{self.n_learners}" if self.n_learners > 1 else "C-ICRL",
                       initial=start, total=outer_iterations)
            it = bar
        for _ in it:
            info = self.outer_step()
            if bar is not None:
                bar.set_postfix(lam=f"{info['multiplier'][0]:.2f}",
                                procs=info["inner_processes"])
            for cb in self._active:
                cb.on_outer_end(self, info)
        return self.state

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue bit for bit (tensors, ints, lists only; a
        stateful learner model's solvers under ``learner_model``)."""
        st = self.state
        sd = {
            "cost_weights": st.cost_weights, "eta": st.eta, "eta_bar": st.eta_bar,
            "tracker": st.tracker, "last_lga": st.last_lga,
            "outer_iteration": st.outer_iteration, "groups": st.groups,
            "solves": self.solves, "history": self.history,
            "fingerprint": self.fingerprint(),
        }
        if getattr(self.learner_model, "stateful", False):
            sd["learner_model"] = self.learner_model.state_dict()
        if hasattr(self.comm, "state_dict"):
            sd["communicator"] = self.comm.state_dict()
        return sd

    def load_state_dict(self, sd: dict) -> None:
        if sd.get("fingerprint") != self.fingerprint():
            raise ValueError("This checkpoint was written by a differently configured trainer "
                             f"(checkpoint {sd.get('fingerprint')!r}, trainer "
                             f"{self.fingerprint()!r}); resume with the same configuration.")
        if getattr(self.learner_model, "stateful", False):
            if "learner_model" not in sd:
                raise ValueError("This checkpoint holds no state of the learners' solvers, "
                                 "which this (stateful) learner model needs to continue; "
                                 "start the run over without resume=true.")
            self.learner_model.load_state_dict(sd["learner_model"])
        self.state = LearnerState(
            cost_weights=sd["cost_weights"], eta=sd["eta"], eta_bar=sd["eta_bar"],
            tracker=sd["tracker"], last_lga=sd["last_lga"],
            outer_iteration=int(sd["outer_iteration"]), groups=sd["groups"])
        self.solves, self.history = int(sd["solves"]), list(sd["history"])
        if "communicator" in sd and hasattr(self.comm, "load_state_dict"):
            self.comm.load_state_dict(sd["communicator"])

    def fingerprint(self) -> str:
        """Shapes and settings a checkpoint must match."""
        lm = self.learner_model
        return (f"NL={self.n_learners} local={self.local} d={lm.cost_dim} lr={lm.reward_dim} "
                f"K={self.K} steps={self.steps} rho={self.rho} prune={self.prune_accrued} "
                f"inner={self.inner_method}:{self.inner_step} "
                f"m={self.m.tolist()} {lm.describe()}"
                + (" merged-stateful-inner" if self._merged_stateful else "")
                + (f" {comm}" if (comm := getattr(self.comm, "describe", lambda: "")()) else ""))

    # ------------------------------------------------------------------ outputs
    def policy(self, i: int) -> ModelSolution:
        """Local learner ``i``'s learned policy π_{η̄, ω_c} (for the tabular model a
        :class:`~dicrl_torch.algos.models.TabularSolution`)."""
        return self.solve(i, self.state.eta_bar[i], self.state.cost_weights[i])

    def prune_constraints(self, i: int, threshold: float = 0.5, min_gain: float = 1e-3,
                          progress: bool = False) -> tuple[torch.Tensor, list[int]]:
        """Keep only the learned constraints that the data supports.

        Backward elimination over the features with ``ω_c,j >= threshold``, weakest
        (smallest ``ω_c,j``, then lowest index) first: feature ``j`` is dropped (set to 0)
        when the constraints left without it still explain learner ``i``'s own
        demonstrations to within ``min_gain`` nats per trajectory of the trained set.
        The bound is on the whole pruned set, not on each feature alone: two constraints
        that block the same route are each redundant while the other stays, so dropping
        every individually redundant one at once can open the route (measured: with soft
        experts two learners dropped both (4,0) and (5,0) and froze at the wall). This is
        Scobee & Sastry's stopping rule read backwards: the smallest set, found greedily,
        whose likelihood is within ``min_gain`` of the learned one.

        Returns:
            (pruned ω_c ``[d]``, indices of the pruned features in the order dropped).
        """
        eta = self.state.eta_bar[i]
        kept = self.state.cost_weights[i].clone()

        def ll(w: torch.Tensor) -> float:
            self.solves += 1
            return self.learner_model.log_likelihood(i, eta, w, self.shards[i])

        base = ll(kept)
        m = self.stats[i].m
        above = torch.from_numpy(learned_constraints(kept, threshold))  # the table's rule
        candidates = sorted(torch.nonzero(above).flatten().tolist(),
                            key=lambda j: (float(kept[j]), j))
        if progress:
            from tqdm.auto import tqdm
            candidates = tqdm(candidates, desc=f"prune learner {i + 1}", leave=False)
        pruned = []
        for j in candidates:
            trial = kept.clone()
            trial[j] = 0.0
            if (base - ll(trial)) / m < min_gain:
                kept = trial
                pruned.append(j)
        return kept, pruned

    def network_or(self, masks: torch.Tensor) -> torch.Tensor:
        """``[d]`` bool: the OR over every learner of a per-learner mask (a collective:
        every learner process must call it, with the same d). ``masks`` ``[n_local, d]``
        bool of the local learners, e.g. the cost features each one's shard accrues.

        Sent as field ``"demonstrated"``, counted in the outer round: 52 bits to a float64
        word (integers below 2**53 are exact), so a 91-feature mask is 16 bytes.
        """
        masks = torch.as_tensor(masks, dtype=torch.bool)
        n = len(self.local)
        if masks.dim() != 2 or masks.shape[0] != n or masks.shape[1] == 0:
            raise ValueError(f"masks must be [{n}, d] bool (one row per local learner "
                             f"{self.local}), got {tuple(masks.shape)}.")
        d = masks.shape[1]
        words = -(-d // _MASK_BITS)
        bits = torch.zeros(n, words * _MASK_BITS, dtype=torch.int64)
        bits[:, :d] = masks.to(torch.int64)
        place = 2 ** torch.arange(_MASK_BITS, dtype=torch.int64)
        packed = (bits.reshape(n, words, _MASK_BITS) * place).sum(-1)  # [n, words]
        gathered = self.comm.all_gather(packed.to(torch.float64), "demonstrated")
        unpacked = (gathered.to(torch.int64)[..., None] // place) % 2  # [N_L, words, 52]
        return unpacked.reshape(self.n_learners, -1)[:, :d].any(0).to(torch.bool)

    def disagreement(self, field: str = "cost_weights") -> float:
        """Max pairwise distance over all learners (a collective: every learner process
        must call it).

        Args:
            field: ``"cost_weights"``: ‖ω_c^[v] − ω_c^[v']‖, which the outer consensus
                drives to 0; ``"eta"``: ‖η̄^[v] − η̄^[v']‖ of the last inner processes'
                outputs (``η̄ = (ω_r, λ)``), which only the inner graph W(k) mixes, so a
                sparse or slowly mixing inner graph shows here.
        """
        values = {"cost_weights": self.state.cost_weights, "eta": self.state.eta_bar}
        if field not in values:
            raise ValueError(f"field must be one of {sorted(values)}, got {field!r}.")
        gathered = self.comm.all_gather(values[field], field, phase="diagnostics")
        return float(torch.cdist(gathered, gathered).max())
