"""ME-greedy and MCE-greedy constraint inference (the paper's §6.1 baselines).

Scobee & Sastry (ICLR 2020) infer constraints greedily, *given the true reward*: among
the candidate constraints — indicator cost features that no demonstration accrues —
add the one the current model expects to accrue most, enforce it by masking, and stop
when the data's likelihood stops improving. One mechanism serves both baselines; only
the model of the demonstrator differs:

- ``model="me"`` (ME-greedy, Scobee's own): the trajectory-level maximum-entropy model
  (Ziebart et al., 2008), ``FactoredSoftBellman.solve(..., backup="trajectory")``.
- ``model="mce"`` (MCE-greedy, the paper's extension): the maximum-*causal*-entropy
  (soft-Bellman) model, ``backup="causal"``, suited to stochastic dynamics.

For deterministic dynamics (and the grid world's point-mass P0) the two coincide:
values, policies, occupancies and likelihoods (tested).

**Enforcing a constraint set C.** ``r(s, a) = -inf`` wherever some ``j ∈ C`` has
``φ_j(s, a) > 0`` (features are non-negative), and ``V_T(s) = -inf`` wherever a *state*
feature of C is positive (a feature whose per-expert tables do not vary with the
action, e.g. a cell or the collision): nothing is scored at the last state, so
without it the final move could still enter a forbidden cell
(``dicrl_torch.solvers.experts`` does the same for the experts).

**Candidates.** A feature is a candidate when no demonstration accrues it at any
``(s_t, a_t)``, ``t < T``, nor — for state features, which the terminal mask also
covers — at ``s_T``. Under the ME model masking a candidate never makes a demonstration
impossible (its tilted dynamics simply avoid the masked outcomes). Under the MCE model
with stochastic dynamics it can: a hard mask makes every action that *risks* entering a
forbidden state impossible (``E[V'] = -inf``), so a demonstration that took such an
action and slipped has likelihood 0. Such a candidate contradicts the data: it is
recorded as infeasible, never added, and the greedy moves on to the next one.

**Log-likelihood** (mean over the demonstrations, nats per trajectory), the same
γ-discounted convention as the D-ICRL objective ``F = Σ_t γ^t ln π_t(a_t|s_t)``:

- MCE: :func:`dicrl_torch.algos.icrl.log_likelihood` ``/ m``.
- ME: the model's step-``t`` conditional is ``π_t(a|s) P̃_t(s'|s, a)`` with the tilted
  dynamics ``P̃_t = P exp(V_{t+1}(s') − L_t(s, a))`` (``dicrl_torch.solvers.factored``).
  Weighting ``ln π_t`` by ``γ^t`` and ``ln P̃_t`` by ``γ^{t+1}`` (the discount of the
  state it produces, as in the solver's variational objective), and with
  ``Q_t − V_t = r + γL_t − V_t``, the sum telescopes::

      Σ_t γ^t (r_t + γ L_t − V_t(s_t)) + γ^{t+1} (ln P + V_{t+1}(s_{t+1}) − L_t)
          = Σ_t γ^t r(s_t, a_t) + γ^T V_T(s_T) − V_0(s_0) + Σ_t γ^{t+1} ln P(s_{t+1}|s_t, a_t)

  and the initial tilt ``P̃_0 ∝ P0 e^{V_0}`` turns ``−V_0(s_0)`` into ``−log Z``,
  ``log Z = log Σ_s P0(s) e^{V_0(s)}``. The ``ln P`` and ``ln P0`` terms do not depend
  on the model and are dropped, as the MCE likelihood drops them. At ``γ = 1`` this is
  Ziebart's ``R(ζ) − log Z``. (For deterministic dynamics the MCE sum telescopes to the
  same expression, hence the coincidence.)

Since the empirical distribution's entropy is fixed, the increase of the mean
log-likelihood *is* the decrease of ``KL(P̂_D ‖ P_model)`` (exactly at ``γ = 1``; for
``γ < 1``, of its γ-weighted per-step analogue). The greedy stops when adding the next
candidate would improve it by less than ``epsilon`` nats per trajectory (that
candidate is then not added), when no feasible candidate has a non-negligible
expected accrual, or at ``max_constraints``. ``m ε`` is the total log-likelihood ratio
a constraint must earn over ``m`` trajectories; the default ``ε = ln(m) / (2m)`` is
BIC's price of one more parameter (0.023 nats per trajectory for ``m = 100``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from dicrl_torch.algos.icrl import log_likelihood as causal_log_likelihood
from dicrl_torch.demos.features import discounted_feature_sums
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import TabularGridModel, encode_joint
from dicrl_torch.features.bases import FactoredFeatures, FactoredReward, FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman, SoftBellmanSolution

# A feature counts as accrued / positive when above this (features are >= 0 and the
# demonstrations' sums are exact).
_POSITIVE = 0.0
# Model accruals at or below this are float noise (the solver's exp floor leaves
# ~1e-35 on masked or unreachable pairs): such a feature is not worth a solve.
_NEGLIGIBLE_ACCRUAL = 1e-9


# ------------------------------------------------------------------- likelihoods
def trajectory_log_likelihood(solution: SoftBellmanSolution, demos: Demonstrations) -> float:
    """``Σ_ζ [Σ_t γ^t r(s_t, a_t) + γ^T V_T(s_T) − log Z] / τ`` of ``demos`` under a
    trajectory-backup (ME) solution, in nats (see the module docstring).

    Returns ``-inf`` when a demonstration takes a masked pair or ends in a masked state.

    Raises:
        ValueError: ``solution`` was not solved with ``backup="trajectory"``.
    """
    if solution.backup != "trajectory":
        raise ValueError(f"trajectory_log_likelihood needs a solution of "
                         f"solve(..., backup='trajectory'), got backup={solution.backup!r}; "
                         f"use dicrl_torch.algos.icrl.log_likelihood for the causal model.")
    model = solution.solver.model
    _check_demos(model, demos)
    reward = solution.reward
    gamma, T = model.gamma, model.horizon
    cells = torch.tensor(demos.states)  # [m, T+1, N]
    acts = torch.tensor(demos.actions)  # [m, T, N]
    N = model.n_experts
    r = sum(reward.local[i][cells[:, :-1, i], acts[:, :, i]].double() for i in range(N))
    if reward.joint is not None:
        r = r + reward.joint.double()[encode_joint(cells[:, :-1], model.n_cells)]
    disc = gamma ** torch.arange(T, dtype=torch.float64)
    ret = (r * disc).sum(1)  # [m]
    v_T = solution.V[T].double().cpu()[tuple(cells[:, T].t())]  # [m]
    total = ret + gamma**T * v_T - solution.log_partition
    return float(total.sum()) / solution.temperature


def _check_demos(model: TabularGridModel, demos: Demonstrations) -> None:
    if not isinstance(demos, Demonstrations):
        raise TypeError(f"demonstrations must be a Demonstrations, got {type(demos).__name__}.")
    if (demos.n_experts, demos.n_cells, demos.horizon) != (
            model.n_experts, model.n_cells, model.horizon):
        raise ValueError(
            f"Demonstrations of {demos.n_experts} experts on {demos.n_cells} cells over "
            f"T={demos.horizon} do not match the solver's model ({model.n_experts} experts, "
            f"{model.n_cells} cells, T={model.horizon}); sample them from this model.")


@dataclass(frozen=True)
class DemonstratorModel:
    """One kind of demonstrator model: the solver backup and its log-likelihood
    ``(solution, demos) -> Σ_ζ ln P(ζ)`` (model-independent terms dropped)."""

    name: str
    backup: str
    log_likelihood: Callable[[SoftBellmanSolution, Demonstrations], float]


MODELS: dict[str, DemonstratorModel] = {
    "mce": DemonstratorModel("MCE", "causal", causal_log_likelihood),
    "me": DemonstratorModel("ME", "trajectory", trajectory_log_likelihood),
}


# ----------------------------------------------------------------- masks
def is_state_feature(features: FactoredFeatures) -> torch.Tensor:
    """``[l]`` bool: features whose value depends on the joint state only (per-expert
    tables constant along the action axis; the joint part is state-only).

    A pass over all ``N·S1·A1·l`` entries: callers that need it repeatedly for the same
    features (a greedy, a classification) compute it once and pass it on
    (``state_features=`` of :func:`constraint_masks`)."""
    local = features.local
    return (local == local[:, :, :1]).all(dim=(0, 1, 2))


def constraint_masks(features: FactoredFeatures, selected: torch.Tensor,
                     model: TabularGridModel, *, state_features: torch.Tensor | None = None
                     ) -> tuple[FactoredReward, torch.Tensor | None]:
    """The hard masks of a constraint set.

    Args:
        features: cost features (non-negative), ``local [N, S1, A1, l]``.
        selected: ``[l]`` bool, the constraint set C.
        model: the tabular model (for the state shape).
        state_features: ``is_state_feature(features)`` if already known (it is computed
            otherwise).

    Returns:
        ``(mask, terminal)``: a :class:`FactoredReward` that is ``-inf`` on every pair
        where some ``j ∈ C`` is positive and 0 elsewhere, and the terminal value
        ``[S1]*N`` (``-inf`` where a state feature of C is positive), or None when C has
        no state feature.
    """
    if selected.shape != (features.dim,) or selected.dtype != torch.bool:
        raise ValueError(f"selected must be a [{features.dim}] bool mask, got "
                         f"{tuple(selected.shape)} {selected.dtype}.")
    hit = (features.local[..., selected] > _POSITIVE).any(-1)  # [N, S1, A1]
    local = torch.zeros(hit.shape, dtype=torch.float64).masked_fill(hit, -math.inf)
    joint = joint_hit = None
    if features.joint is not None:
        cols = selected[features.joint_columns]
        if cols.any():
            joint_hit = (features.joint[:, cols] > _POSITIVE).any(-1)  # [S]
            joint = torch.zeros(joint_hit.shape, dtype=torch.float64).masked_fill(
                joint_hit, -math.inf)
    if state_features is None:
        state_features = is_state_feature(features)
    state_sel = selected & state_features
    if not state_sel.any():
        return FactoredReward(local=local, joint=joint), None
    cell_bad = (features.local[:, :, 0][..., state_sel] > _POSITIVE).any(-1)  # [N, S1]
    bad = cells_or_joint(cell_bad, joint_hit, model)
    terminal = torch.zeros(model.state_shape, dtype=torch.float64).masked_fill(bad, -math.inf)
    return FactoredReward(local=local, joint=joint), terminal


def cells_or_joint(cell: torch.Tensor, joint: torch.Tensor | None,
                   model: TabularGridModel) -> torch.Tensor:
    """``[S1]*N`` bool: the joint states where some expert ``i`` is on a cell with
    ``cell[i]`` (``[N, S1]`` bool) or where ``joint`` (``[S]`` bool, or None) holds."""
    N, S1 = model.n_experts, model.n_cells
    bad = cell[0].reshape([S1] + [1] * (N - 1))
    for i in range(1, N):
        shape = [1] * N
        shape[i] = S1
        bad = bad | cell[i].reshape(shape)
    bad = bad.expand(model.state_shape)
    if joint is not None:
        bad = bad | joint.reshape(model.state_shape)
    return bad.contiguous()


def demonstrated_features(features: FactoredFeatures, demos: Demonstrations,
                          gamma: float, *, state_features: torch.Tensor | None = None
                          ) -> torch.Tensor:
    """``[l]`` bool: features some demonstration accrues at a ``(s_t, a_t)``, or — for
    state features — at its final state ``s_T`` (``state_features``:
    ``is_state_feature(features)`` if already known)."""
    sums = discounted_feature_sums(features, demos, gamma)  # [m, l]
    seen = (sums > _POSITIVE).any(0)
    last = torch.tensor(demos.states[:, -1])  # [m, N]
    phi_T = features.at(last, torch.zeros_like(last), demos.n_cells)  # [m, l]
    if state_features is None:
        state_features = is_state_feature(features)
    return seen | ((phi_T > _POSITIVE).any(0) & state_features)


def cost_features_of(cost_basis, model: TabularGridModel
                     ) -> tuple[FactoredFeatures, list[str]]:
    """A cost basis (or its features) checked against the solver's ``model``: its
    :class:`FactoredFeatures` ``[N, S1, A1, l]`` (+ joint part) and feature names.

    Raises:
        TypeError, ValueError: naming the mismatch and the fix.
    """
    if isinstance(cost_basis, FeatureBasis):
        other = cost_basis.model
        if other is not model and (other.layout != model.layout
                                   or other.n_experts != model.n_experts):
            raise ValueError(
                f"The cost basis {type(cost_basis).__name__} was built on another model "
                f"(layout {other.layout.name!r}, {other.layout.size}x{other.layout.size}, "
                f"{other.n_experts} experts) than the solver's (layout "
                f"{model.layout.name!r}, {model.layout.size}x{model.layout.size}, "
                f"{model.n_experts} experts); build it on solver.model, e.g. "
                f"SharedIndicatorCostBasis(solver.model).")
        features, names = cost_basis(), list(cost_basis.names)
    elif isinstance(cost_basis, FactoredFeatures):
        features, names = cost_basis, [f"feature {j}" for j in range(cost_basis.dim)]
    else:
        raise TypeError(f"cost_basis must be a FeatureBasis or FactoredFeatures, got "
                        f"{type(cost_basis).__name__}.")
    want = (model.n_experts, model.n_cells, model.n_actions)
    if tuple(features.local.shape[:3]) != want:
        raise ValueError(f"The cost features are for {tuple(features.local.shape[:3])} "
                         f"(experts, cells, actions), the solver's model has {want}; build "
                         f"the basis on solver.model.")
    if features.joint is not None and features.joint.shape[0] != model.n_states:
        raise ValueError(f"The cost features' joint part covers {features.joint.shape[0]} "
                         f"joint states, the solver's model has {model.n_states}; build the "
                         f"basis on solver.model.")
    return features, names


# ----------------------------------------------------------------- the greedy
@dataclass(frozen=True)
class GreedyStep:
    """One candidate the greedy evaluated.

    Attributes:
        feature: its index; name: its label.
        accrual: the current model's expected discounted accrual of it.
        log_likelihood: mean log-likelihood per demonstration with it added.
        improvement: increase of that mean (= decrease of the KL) it brings.
        accepted: whether it was added (``improvement >= epsilon``).
        infeasible: whether it contradicts a demonstration (likelihood ``-inf``).
        seconds: wall time of the solve and likelihood.
    """

    feature: int
    name: str
    accrual: float
    log_likelihood: float
    improvement: float
    accepted: bool
    infeasible: bool
    seconds: float


class ResumeMismatchError(ValueError):
    """A saved greedy progress record cannot be continued by this greedy."""


@dataclass
class GreedyResult:
    """Output of :meth:`GreedyLoop.run`.

    Attributes:
        constraint_mask: ``[l]`` bool, the learned constraints.
        added: indices of the added features, in order; ``added_names`` their labels.
        log_likelihood: ``[k+1]`` mean log-likelihood per demonstration after
            0, 1, .., k constraints (entry 0: the unconstrained model).
        improvement: ``[k]`` per accepted step, the increase of that mean (= the KL
            decrease), for curves over iterations.
        steps: every evaluated candidate: the accepted ones, infeasible ones and the
            rejected last one.
        solution: the final model (grid: a :class:`SoftBellmanSolution` with occupancies,
            ``solution.policy_at`` rolls out with ``dicrl_torch.metrics.rollout_true_cmg``;
            drones: a ``SACSolution``).
        terminal_value: ``[S1]*N`` terminal mask of the final model (or None).
        stop_reason: why the greedy stopped.
        model: ``"me"`` or ``"mce"``.
        seconds: wall time of the search, summed over resumed runs (their re-solves of
            the saved set left out).
    """

    constraint_mask: torch.Tensor
    added: list[int]
    added_names: list[str]
    log_likelihood: list[float]
    improvement: list[float]
    steps: list[GreedyStep]
    solution: Any
    terminal_value: torch.Tensor | None
    stop_reason: str
    model: str
    seconds: float = 0.0


class GreedyLoop:
    """Scobee & Sastry's greedy loop, independent of the model of the demonstrator.

    A subclass sets ``candidates`` ``[l]`` bool, ``names``, ``epsilon``,
    ``max_constraints``, ``progress``, ``label`` and ``model_name`` and implements
    :meth:`solve`, :meth:`mean_log_likelihood` and :meth:`expected_accrual`; a
    stateful model (a warm-started policy) also overrides :meth:`accept` and sets
    ``resumable = False``: its model is more than the constraint set, so a run cannot
    be continued from a saved :meth:`run` progress record.
    """

    candidates: torch.Tensor
    names: list[str]
    epsilon: float
    max_constraints: int
    progress: bool
    label: str
    model_name: str
    resumable: bool = True
    # How close a resumed run's re-solved log-likelihood must come to the saved one.
    resume_rel_tol: float = 1e-9

    def solve(self, selected: torch.Tensor) -> tuple[Any, Any]:
        """The model with constraint set ``selected`` ``[l]`` bool: (solution, extra)."""
        raise NotImplementedError

    def mean_log_likelihood(self, solution: Any) -> float:
        raise NotImplementedError

    def expected_accrual(self, solution: Any) -> torch.Tensor:
        """``[l]`` the model's expected discounted accrual of each feature."""
        raise NotImplementedError

    def accept(self, solution: Any, extra: Any) -> None:
        """Called when ``solution`` becomes the current model (a no-op by default)."""

    def run(self, *, resume_from: dict | None = None,
            on_step: Callable[[dict], None] | None = None) -> GreedyResult:
        """Add constraints greedily until the stopping rule (module docstring) holds.

        Args:
            resume_from: a progress record that ``on_step`` gave an earlier run of the
                same problem and settings (e.g. read back from a checkpoint). The loop
                re-solves the model of its constraint set and goes on from there, so it
                ends as the uninterrupted run does; a finished record is only re-solved.
            on_step: called with the progress record after every evaluated candidate
                and once more if the loop then stops without evaluating one. The record
                holds only tensors, numbers, strings and lists (``torch.save`` and
                ``torch.load(weights_only=True)`` keep it); ``evaluated`` (candidates
                tried) plus ``finished`` grows by one at each call.

        Raises:
            ResumeMismatchError: ``resume_from`` belongs to another problem or other
                settings, or the model cannot be resumed.
        """
        t_start = time.perf_counter()
        if resume_from is None:
            selected = torch.zeros(len(self.candidates), dtype=torch.bool)
            infeasible = torch.zeros_like(selected)
            added, lls, gains, steps, stop, seconds_before = [], [], [], [], None, 0.0
        else:
            selected, infeasible, added, lls, gains, steps, stop, seconds_before = \
                self._restore(resume_from)
        sol, extra = self.solve(selected)
        self.accept(sol, extra)
        ll = self.mean_log_likelihood(sol)
        if resume_from is None:
            lls = [ll]
        elif not math.isclose(ll, lls[-1], rel_tol=self.resume_rel_tol, abs_tol=1e-9):
            raise ResumeMismatchError(
                f"The saved {self.label} progress does not belong to this problem: its "
                f"constraint set has mean log-likelihood {lls[-1]:.9g} there and {ll:.9g} "
                f"here (another reward, solver or set of demonstrations). Start the "
                f"greedy over.")
        ll = lls[-1]  # the saved number exactly: the resumed run repeats the uninterrupted one
        if resume_from is not None:
            # Re-solving the saved set is the cost of resuming, not of the search: leaving
            # it out keeps `seconds` from growing each time a finished search is resumed.
            t_start = time.perf_counter()

        def report() -> None:
            if on_step is not None:
                on_step(self._record(selected, infeasible, added, lls, gains, steps, stop,
                                     seconds_before + time.perf_counter() - t_start))

        bar = None
        if self.progress and stop is None:
            from tqdm.auto import tqdm
            total = min(self.max_constraints, int(self.candidates.sum()))
            bar = tqdm(total=total, initial=len(added), desc=self.label)
        while stop is None:
            if len(added) >= self.max_constraints:
                stop = "max_constraints reached"
                report()
                break
            accrual = self.expected_accrual(sol)  # [l]
            open_ = self.candidates & ~selected & ~infeasible & (accrual > _NEGLIGIBLE_ACCRUAL)
            if not open_.any():
                stop = "no feasible candidate left with non-negligible expected accrual"
                report()
                break
            j = int(torch.where(open_, accrual, -math.inf).argmax())
            t0 = time.perf_counter()
            trial = selected.clone()
            trial[j] = True
            new_sol, new_extra = self.solve(trial)
            new_ll = self.mean_log_likelihood(new_sol)
            gain = new_ll - ll
            bad = new_ll == -math.inf  # contradicts a demonstration (module docstring)
            accepted = not bad and gain >= self.epsilon
            steps.append(GreedyStep(feature=j, name=self.names[j], accrual=float(accrual[j]),
                                    log_likelihood=new_ll, improvement=gain, accepted=accepted,
                                    infeasible=bad, seconds=time.perf_counter() - t0))
            if bad:
                infeasible[j] = True  # more masks only keep it impossible: never retry
            elif not accepted:
                stop = f"improvement {gain:.3g} < epsilon {self.epsilon:g}"
            else:
                selected, sol, extra, ll = trial, new_sol, new_extra, new_ll
                self.accept(sol, extra)
                added.append(j)
                lls.append(ll)
                gains.append(gain)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(added=self.names[j], ll=f"{ll:.2f}")
            report()
        if bar is not None:
            bar.close()
        return GreedyResult(constraint_mask=selected, added=added,
                            added_names=[self.names[j] for j in added], log_likelihood=lls,
                            improvement=gains, steps=steps, solution=sol,
                            terminal_value=extra if isinstance(extra, torch.Tensor) else None,
                            stop_reason=stop, model=self.model_name,
                            seconds=seconds_before + time.perf_counter() - t_start)

    # ------------------------------------------------------------------ progress records
    def _settings(self) -> dict:
        """What a progress record must have been made with to be continued here."""
        return {"model": self.model_name, "epsilon": self.epsilon,
                "max_constraints": self.max_constraints}

    def _record(self, selected, infeasible, added, lls, gains, steps, stop, seconds) -> dict:
        return {**self._settings(), "candidates": self.candidates.clone(),
                "selected": selected.clone(), "infeasible": infeasible.clone(),
                "added": list(added), "log_likelihood": list(lls), "improvement": list(gains),
                "steps": [dataclasses.asdict(s) for s in steps], "stop_reason": stop,
                "seconds": seconds, "evaluated": len(steps), "finished": stop is not None}

    def _restore(self, record: dict) -> tuple:
        if not self.resumable:
            raise ResumeMismatchError(
                f"{self.label} cannot be resumed: its model is more than the constraint set "
                f"(a warm-started policy). Run it from the start.")
        missing = sorted({"candidates", "selected", "infeasible", "added", "log_likelihood",
                          "improvement", "steps", "stop_reason", "seconds"}
                         - set(record))
        if missing:
            raise ResumeMismatchError(
                f"The saved {self.label} progress lacks {missing}; it was not written by "
                f"GreedyLoop.run. Start the greedy over.")
        theirs = {k: record.get(k) for k in self._settings()}
        if theirs != self._settings():
            raise ResumeMismatchError(
                f"The saved {self.label} progress was made with {theirs}, this run has "
                f"{self._settings()}. Continue it with its settings, or start the greedy "
                f"over.")
        if not torch.equal(torch.as_tensor(record["candidates"]), self.candidates):
            raise ResumeMismatchError(
                f"The saved {self.label} progress has other candidate constraints than this "
                f"problem (another cost basis or other demonstrations). Start the greedy "
                f"over.")
        steps = [GreedyStep(**s) for s in record["steps"]]
        return (record["selected"].clone(), record["infeasible"].clone(), list(record["added"]),
                list(record["log_likelihood"]), list(record["improvement"]), steps,
                record["stop_reason"], float(record["seconds"]))


class GreedyConstraintInference(GreedyLoop):
    """Greedy constraint inference with a given reward (ME-greedy / MCE-greedy).

    Args:
        solver: the factored solver of the learner's model (nominal dynamics).
        reward: the true reward as a :class:`FactoredReward` (the baselines are given it).
        cost_basis: the candidate features: a :class:`FeatureBasis` (labels from its
            ``names``) or :class:`FactoredFeatures`; non-negative (indicators).
        demonstrations: all demonstrations (the baselines are centralised).
        model: ``"me"`` (trajectory maximum entropy) or ``"mce"`` (maximum causal
            entropy).
        epsilon: stop when the next candidate raises the mean log-likelihood by less
            than this many nats per trajectory; None: ``ln(m) / (2m)`` (BIC, module
            docstring).
        max_constraints: at most this many constraints (None: no limit).
        progress: show a tqdm bar over greedy steps.
    """

    def __init__(self, *, solver: FactoredSoftBellman, reward: FactoredReward,
                 cost_basis: FeatureBasis | FactoredFeatures, demonstrations: Demonstrations,
                 model: str = "mce", epsilon: float | None = None,
                 max_constraints: int | None = None, progress: bool = False) -> None:
        if model not in MODELS:
            raise ValueError(f"model must be one of {sorted(MODELS)} ('me': ME-greedy, "
                             f"'mce': MCE-greedy), got {model!r}.")
        if epsilon is not None and not (epsilon >= 0.0 and math.isfinite(epsilon)):
            raise ValueError(f"epsilon must be a finite number >= 0 (nats per trajectory), "
                             f"got {epsilon!r}.")
        if max_constraints is not None and (not isinstance(max_constraints, int)
                                            or max_constraints < 0):
            raise ValueError(f"max_constraints must be None or an int >= 0, got "
                             f"{max_constraints!r}.")
        if not isinstance(reward, FactoredReward):
            raise TypeError(f"reward must be a FactoredReward (e.g. "
                            f"reward_basis().weighted(w_true)), got {type(reward).__name__}.")
        m = solver.model
        features, names = cost_features_of(cost_basis, m)
        if features.local.min() < 0 or (features.joint is not None and features.joint.min() < 0):
            raise ValueError("cost features must be non-negative: a constraint masks the pairs "
                             "where its feature is positive. Use an indicator basis.")
        _check_demos(m, demonstrations)
        self.solver, self.reward, self.features, self.names = solver, reward, features, names
        self.demos = demonstrations
        if solver.dtype == torch.float32:
            # float32 sums round differently on another CPU's vector width (compiled
            # kernels) or thread count: a resumed record from another machine is the same
            # problem to ~1e-7; another problem differs by far more.
            self.resume_rel_tol = 1e-5
        self.kind = MODELS[model]
        self.model_name = model
        m_demo = demonstrations.n_trajectories
        self.epsilon = math.log(m_demo) / (2 * m_demo) if epsilon is None else float(epsilon)
        self.max_constraints = features.dim if max_constraints is None else max_constraints
        self.progress = progress
        self.label = f"{self.kind.name}-greedy"
        self.state_features = is_state_feature(features)  # [l], once: every solve masks
        self.candidates = ~demonstrated_features(features, demonstrations, m.gamma,
                                                 state_features=self.state_features)  # [l]
        self.solves = 0

    # ------------------------------------------------------------------ pieces
    def solve(self, selected: torch.Tensor) -> tuple[SoftBellmanSolution, torch.Tensor | None]:
        """The model with constraint set ``selected`` ``[l]`` bool, with occupancies."""
        mask, terminal = constraint_masks(self.features, selected, self.solver.model,
                                          state_features=self.state_features)
        self.solves += 1
        sol = self.solver.solve(self.reward + mask, terminal_value=terminal,
                                backup=self.kind.backup)
        return sol, terminal

    def mean_log_likelihood(self, solution: SoftBellmanSolution) -> float:
        """Mean log-likelihood per demonstration (nats) under the chosen model."""
        return self.kind.log_likelihood(solution, self.demos) / self.demos.n_trajectories

    def expected_accrual(self, solution: SoftBellmanSolution) -> torch.Tensor:
        return solution.feature_expectation(self.features)


def me_greedy(**kwargs) -> GreedyResult:
    """ME-greedy (Scobee & Sastry): :class:`GreedyConstraintInference` with
    ``model="me"``; keyword arguments as there."""
    return GreedyConstraintInference(model="me", **kwargs).run()


def mce_greedy(**kwargs) -> GreedyResult:
    """MCE-greedy (the paper's extension): :class:`GreedyConstraintInference` with
    ``model="mce"``; keyword arguments as there."""
    return GreedyConstraintInference(model="mce", **kwargs).run()


# ----------------------------------------------------------------- evaluation
def reachable_constraints(*, solver: FactoredSoftBellman, reward: FactoredReward,
                          cost_basis: FeatureBasis | FactoredFeatures, true_mask: torch.Tensor,
                          min_accrual: float = 0.01) -> torch.Tensor:
    """``[l]`` bool: the true constraints the nominal model would meet.

    A true constraint feature is *reachable* when the unconstrained maximum-causal-
    entropy model of the true reward (temperature 1, no mask: both greedy methods'
    starting point in the stochastic case, and the one every constraint must be
    learned against) accrues it with expected discounted count
    ``E[Σ_t γ^t φ_j] >= min_accrual``. A constraint below that is one the demonstrations
    carry (almost) no evidence of: no learner that only sees how the experts behave
    can be blamed for missing it.
    """
    features = cost_basis() if isinstance(cost_basis, FeatureBasis) else cost_basis
    sol = solver.solve(reward, backup="causal")
    mu = sol.feature_expectation(features)
    return true_mask.bool() & (mu >= min_accrual)


class SACGreedyConstraintInference(GreedyLoop):
    """M(C)E-greedy on a continuous game (the paper's: the drone arena), with the
    SAC-style solver as the model.

    The paper's §6.2 protocol: the greedy is given the reward learned by D-ICRL
    (``ω_r``), all pairs pooled. A constraint set C is enforced by the penalty
    ``−penalty · Σ_{j∈C} φ_j`` (a continuous policy cannot be masked), i.e. the solver's
    ``η = [ω_r, −penalty]`` with ``ω_c`` the indicator of C. The arena's noise is small,
    so the ME and MCE models coincide (as the paper says): one row, ``"M(C)E"``.

    Every trial trains a *clone* of the current solver for ``timesteps`` steps; an
    accepted trial's clone becomes the current model, a rejected one is dropped, so the
    warm-started policy always belongs to the accepted constraint set.

    Args:
        solver: a (pre-trained) :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver`.
        reward_weights: ``[l_r]`` the given ``ω_r``.
        demonstrations: all episodes (``ContinuousDemonstrations`` of the solver's game,
            or with ``to_continuous()``, e.g. the arena's ``DroneDemonstrations``).
        penalty: the per-step penalty of entering a constraint (in reward units).
        timesteps: SAC steps per trial.
        epsilon: stop below this gain in nats per pair; None: ``ln(m) / (2m)`` (BIC).
        max_constraints: at most this many (None: no limit).
        progress: a tqdm bar over greedy steps.
    """

    resumable = False  # each trial's policy is warm-started from the last accepted one

    def __init__(self, *, solver, reward_weights, demonstrations, penalty: float = 10.0,
                 timesteps: int = 2000, epsilon: float | None = None,
                 max_constraints: int | None = None, progress: bool = False) -> None:
        from dicrl_torch.solvers.sac import SACConstrainedSolver, discounted_demo_feature_sums

        if not isinstance(solver, SACConstrainedSolver):
            raise TypeError(f"solver must be a SACConstrainedSolver, got {type(solver).__name__}.")
        if not (penalty > 0 and math.isfinite(penalty)):
            raise ValueError(f"penalty must be a positive number, got {penalty!r}.")
        if not isinstance(timesteps, int) or timesteps < 1:
            raise ValueError(f"timesteps must be an int >= 1, got {timesteps!r}.")
        if epsilon is not None and not (epsilon >= 0.0 and math.isfinite(epsilon)):
            raise ValueError(f"epsilon must be a finite number >= 0 (nats per pair), got "
                             f"{epsilon!r}.")
        w = torch.as_tensor(reward_weights, dtype=torch.float64).flatten()
        if w.shape != (solver.l_r,) or not torch.isfinite(w).all():
            raise ValueError(f"reward_weights must be {solver.l_r} finite numbers, got "
                             f"{w.tolist()}.")
        self.solver, self.demos, self.penalty, self.timesteps = solver, demonstrations, \
            float(penalty), timesteps
        self.eta = torch.cat([w, torch.tensor([-self.penalty], dtype=torch.float64)])
        sums = discounted_demo_feature_sums(demonstrations, solver.cost_basis, solver.gamma,
                                            absorbing=solver.absorbing)  # [m, l]
        self.candidates = ~(sums > _POSITIVE).any(0)
        self.names = list(getattr(solver.cost_basis, "names",
                                  [f"feature {j}" for j in range(solver.l_c)]))
        m = demonstrations.n_trajectories
        self.epsilon = math.log(m) / (2 * m) if epsilon is None else float(epsilon)
        self.max_constraints = solver.l_c if max_constraints is None else int(max_constraints)
        self.progress, self.label, self.model_name = progress, "M(C)E-greedy", "m(c)e"
        self._trials = 0

    def solve(self, selected: torch.Tensor):
        self._trials += 1
        trial = self.solver.clone(self.solver.seed + self._trials)
        sol = trial.solve(self.eta, selected.double(), self.timesteps)
        return sol, trial

    def accept(self, solution, extra) -> None:
        self.solver = extra

    def mean_log_likelihood(self, solution) -> float:
        # The policy IS the solver's state: score under the trial's own solver.
        return solution.solver.log_likelihood(self.demos) / self.demos.n_trajectories

    def expected_accrual(self, solution) -> torch.Tensor:
        return solution.mu_c
