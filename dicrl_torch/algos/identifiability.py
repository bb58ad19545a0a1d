"""Which cost features can the demonstrations identify as constraints? (docs/design.md §6)

An evaluation-only analysis: it is given the true reward and the experts' model (their
temperature), which no learner ever sees. For a cost basis, the nominal model, P0 and a
set of demonstrations ``D`` (all that the learners hold together), every feature ``j``
falls in one class:

- **demonstrated**: some trajectory of ``D`` accrues ``φ_j`` (``φ_j > 0`` at a visited
  ``(s_t, a_t)``, ``t < T``, or — for a state feature — at ``s_T``: the rule of
  :func:`dicrl_torch.algos.greedy.demonstrated_features`), or P0 puts mass on a state
  where the state feature ``φ_j`` is positive. With budget 0 such a feature cannot be a
  constraint. ``U`` is the set of the other features.
- **required**: ``j ∈ U`` and the experts' policy, with every *other* feature of ``U``
  enforced as a hard constraint (``U \\ {j}``, masked as
  :func:`dicrl_torch.algos.greedy.constraint_masks` does), still accrues ``φ_j`` with
  probability at least ``min_probability`` (0.01) per trajectory from P0. Even with
  everything else the data leave unseen forbidden the experts would use ``j``, so every
  constraint set consistent with ``D`` must contain it.
- **undetermined**: the rest of ``U``: ``D`` cannot tell whether it is a constraint.

**The probability of accruing a feature** is computed exactly by
:func:`~dicrl_torch.algos.accrual.accrual_probability` (its module says how).

**The experts' model under a constraint set.** The experts of
:func:`~dicrl_torch.solvers.experts.expert_solution` mask the true CMG's constraints;
here the mask is ``U \\ {j}`` instead: ``-inf`` reward on every pair where one of its
features is positive and ``-inf`` terminal value where one of its *state* features is,
solved at the experts' temperature. When the experts cannot avoid ``U \\ {j}`` surely
from some start state of P0 (``V_0 = -inf`` there), the hard-constrained model is
undefined: ``j`` is reported ``undetermined`` with probability NaN and flagged in
``infeasible``.

Two consequences of the finite-horizon model worth knowing when reading the classes:
optimal experts choose uniformly among tied actions, so an undemonstrated action that,
once open, ties with the best demonstrated ones at a state the experts reach (e.g. a
move off the grid, which keeps an expert at its goal as ``stay`` does) takes its share
of the ties and is required; and
at the last decision (``t = T-1``) nothing more is scored, so the experts pick any move
that is safe under ``U \\ {j}``: a feature one move away from where they stand then is
accrued (and the true experts' demonstrations show such last moves too).

**P0.** ``initial_distribution`` is a joint distribution (``[S1]*N``) or one per expert
(``[N, S1]``, independent starts); by default the model's (a point mass on the start
cells, or the product of the varied-start sets). Every demonstration must start where P0 has mass.

**Cost.** One backward solve per classified undemonstrated feature plus the sparse
forward pass (``experiments/studies/identifiability.py`` prints the time per candidate).
What every candidate shares is computed once per classification: where each feature is
positive and which are state features, the masks of ``U \\ {j}`` from counts over ``U``,
the model's move tables; the hard solves of an eager solver run in wider chunks of cells
(:func:`candidate_solver`: the same values, fewer kernel calls). A hard solve runs on the
cells ``U \\ {j}`` leaves open (:func:`~dicrl_torch.solvers.factored.open_cells.solve_hard`:
the same values at every open state, ``(K / S1)^N`` of the work for ``K`` open cells),
so a classification costs less the more cells the data leave unseen, most at 3 experts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from dicrl_torch.algos.accrual import (
    CHUNK_STATES,
    AllButOne,
    Chain,
    Hits,
    Positive,
    accrual_probability,
    as_mask,
    candidate_solver,
    joint_initial_distribution,
    killed_forward,
)
from dicrl_torch.algos.greedy import (
    cost_features_of,
    demonstrated_features,
    is_state_feature,
)
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.grid import TabularGridModel, decode_joint, encode_joint
from dicrl_torch.features.bases import FactoredFeatures, FactoredReward, FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman
from dicrl_torch.solvers.factored.open_cells import solve_hard

__all__ = [
    "Identifiability",
    "accrual_probability",
    "certify_constraints",
    "check_indicator_basis",
    "classify_features",
    "demonstrated_mask",
    "fnr_required",
    "joint_initial_distribution",
]

MIN_PROBABILITY = 0.01
# The learners' certificate (certify_constraints): optimal experts under the learned
# reward, and a threshold ten times below MIN_PROBABILITY (docs/design.md §6).
CERTIFICATE_TEMPERATURE = 0.0
CERTIFICATE_MIN_PROBABILITY = 1e-3


# ------------------------------------------------------------------------ result
@dataclass(frozen=True)
class Identifiability:
    """The classes of a basis's cost features (module docstring).

    ``demonstrated``, ``required`` and ``undetermined`` partition ``scope``: the
    features classified (every feature, or those asked for with ``only``, or a
    :meth:`restrict`-ion).

    Attributes:
        names: ``[l]`` feature labels.
        scope: ``[l]`` bool, the features classified.
        demonstrated, required, undetermined: ``[l]`` bool masks.
        probability: ``[l]`` float64, the probability per trajectory from P0 that the
            experts under ``U \\ {j}`` accrue ``φ_j``; NaN where not computed
            (demonstrated, out of scope, infeasible).
        infeasible: ``[l]`` bool (within ``undetermined``): the experts cannot avoid
            ``U \\ {j}`` surely from P0, so there is no hard-constrained model to ask.
        min_probability: the threshold of ``required``.
        temperature: the experts' temperature (0: optimal, uniform ties).
        seconds: wall time of the classification; ``n_solves`` its backward solves.
        accrued: ``[l]`` bool, every feature a demonstration or P0 accrues, in scope or
            not (a learned constraint among them contradicts the data).
    """

    names: list[str]
    scope: torch.Tensor
    demonstrated: torch.Tensor
    required: torch.Tensor
    undetermined: torch.Tensor
    probability: torch.Tensor
    infeasible: torch.Tensor
    min_probability: float = MIN_PROBABILITY
    temperature: float = 0.0
    seconds: float = 0.0
    n_solves: int = 0
    accrued: torch.Tensor | None = None

    @property
    def n_features(self) -> int:
        """Features classified (``|scope|``)."""
        return int(self.scope.sum())

    @property
    def n_demonstrated(self) -> int:
        return int(self.demonstrated.sum())

    @property
    def n_required(self) -> int:
        return int(self.required.sum())

    @property
    def n_undetermined(self) -> int:
        return int(self.undetermined.sum())

    @property
    def seconds_per_candidate(self) -> float | None:
        """Mean wall time of one candidate (solve + forward pass); None without any."""
        return self.seconds / self.n_solves if self.n_solves else None

    def names_of(self, mask: torch.Tensor) -> list[str]:
        """The labels of the features in ``mask`` ``[l]`` bool."""
        return [self.names[j] for j in torch.nonzero(as_mask(mask, len(self.names),
                                                              "mask")).flatten().tolist()]

    def restrict(self, mask) -> Identifiability:
        """The classification of the features in ``mask`` ``[l]`` bool only (e.g. the
        true constraints, ``cost_basis.true_constraints()``); probabilities outside
        become NaN."""
        mask = as_mask(mask, len(self.names), "mask")
        return replace(self, scope=self.scope & mask, demonstrated=self.demonstrated & mask,
                       required=self.required & mask, undetermined=self.undetermined & mask,
                       infeasible=self.infeasible & mask,
                       probability=torch.where(mask, self.probability, math.nan))

    def summary(self) -> str:
        """One line: the counts and the undetermined features."""
        und = ", ".join(self.names_of(self.undetermined)) or "none"
        return (f"{self.n_features} features: {self.n_demonstrated} demonstrated, "
                f"{self.n_required} required, {self.n_undetermined} undetermined ({und})")

    def as_dict(self) -> dict:
        """A JSON-ready record: counts, the members of each class and the computed
        probabilities by name."""
        prob = {self.names[j]: float(self.probability[j])
                for j in range(len(self.names)) if math.isfinite(self.probability[j])}
        return {
            "n_features": self.n_features, "n_demonstrated": self.n_demonstrated,
            "n_required": self.n_required, "n_undetermined": self.n_undetermined,
            "demonstrated": self.names_of(self.demonstrated),
            "required": self.names_of(self.required),
            "undetermined": self.names_of(self.undetermined),
            "infeasible": self.names_of(self.infeasible),
            "probability": prob, "min_probability": self.min_probability,
            "temperature": self.temperature, "seconds": self.seconds,
            "n_solves": self.n_solves,
        }


def fnr_required(learned, true, result: Identifiability) -> float | None:
    """``|required ∩ true \\ learned| / |required ∩ true|``: the misses among the true
    constraints the data pin down (docs/design.md §6).

    Args:
        learned, true: ``[l]`` bool masks (tensors or arrays); ``true`` may be None.
        result: a classification whose scope covers ``true``.

    Returns:
        The rate, or None when ``true`` is None or no true constraint is required.
    """
    if true is None:
        return None
    l = len(result.names)
    learned, true = as_mask(learned, l, "learned"), as_mask(true, l, "true")
    outside = true & ~result.scope
    if outside.any():
        raise ValueError(f"The classification does not cover the true constraints "
                         f"{result.names_of(outside)}; classify them too (classify_features("
                         f"..., only=None or only=true)).")
    pinned = result.required & true
    n = int(pinned.sum())
    return float((pinned & ~learned).sum()) / n if n else None


# ------------------------------------------------------------------------ classification
def classify_features(*, solver: FactoredSoftBellman, reward: FactoredReward,
                      cost_basis: FeatureBasis | FactoredFeatures,
                      demonstrations: Demonstrations | Sequence[Demonstrations],
                      temperature: float = 0.0, initial_distribution=None,
                      only=None, min_probability: float = MIN_PROBABILITY,
                      last_move: bool = True, also_demonstrated=None,
                      open_overlaps: bool = False,
                      progress: bool = False) -> Identifiability:
    """Classify cost features as demonstrated, required or undetermined (module
    docstring).

    Args:
        solver: the factored solver of the nominal model.
        reward: the experts' true reward (``reward_basis().weighted(w_true)``).
        cost_basis: an indicator basis built on ``solver.model`` (shared, per_expert,
            regions), or its :class:`FactoredFeatures`. Features must be non-negative
            and vanish somewhere: a feature positive everywhere (a frozen random MLP)
            is accrued by every trajectory and no class says anything about it.
        demonstrations: all the demonstrations the learners hold together: one set or
            a sequence of shards.
        temperature: the experts' temperature, the one the demonstrations were sampled
            at (0: optimal experts, uniform over ties).
        initial_distribution: P0, joint ``[S1]*N`` or per expert ``[N, S1]``; default
            the model's P0.
        only: ``[l]`` bool, classify these features only (e.g. the true constraints:
            a solve per undemonstrated one instead of per feature of ``U``); ``U`` is
            still every undemonstrated feature. None: all.
        min_probability: the per-trajectory probability from which an undemonstrated
            feature is required.
        last_move: whether the last move (the action at ``t = T-1``, the state ``s_T``)
            accrues (see :func:`accrual_probability`); "demonstrated" always counts it.
        also_demonstrated: ``[l]`` bool, features known to be demonstrated besides those
            ``demonstrations`` accrue (another learner's shard: :func:`demonstrated_mask`);
            None: none.
        open_overlaps: for a basis whose features overlap (a deep basis' units of
            several sizes, a region beside its cells): while ``j`` is tested, the other
            unseen features of its kind forbid nothing inside ``j``'s support
            (:class:`AllButOne`'s ``open_support``), so that a unit nested in another
            can be tested at all; then every required feature that overlaps narrower
            required ones (:meth:`Positive.overlaps`) is tested again with those
            forbidden inside its support too, narrowest first, and is dropped where it
            is no longer accrued (a coarse unit required only for the fine one inside
            it; one that closes a route no narrower one closes stays). Indicator bases
            have no overlaps: the classes are the same either way.
        progress: a tqdm bar over the candidates.

    Raises:
        ValueError: naming the problem and the fix, for a basis of another model or
            positive everywhere, demonstrations of another grid (cells, actions,
            experts, horizon) or starting where P0 has no mass, no demonstrations, or
            a bad P0, temperature, threshold or mask.
    """
    if not isinstance(solver, FactoredSoftBellman):
        raise TypeError(f"solver must be a FactoredSoftBellman, got {type(solver).__name__}.")
    model = solver.model
    features, names = _features_of(cost_basis, model)
    if not isinstance(reward, FactoredReward):
        raise TypeError(f"reward must be a FactoredReward (e.g. "
                        f"reward_basis().weighted(w_true)), got {type(reward).__name__}.")
    want = (model.n_experts, model.n_cells, model.n_actions)
    if tuple(reward.local.shape) != want:
        raise ValueError(f"reward.local has shape {tuple(reward.local.shape)}, the solver's "
                         f"model needs {want}; build the reward on solver.model.")
    if not (temperature >= 0.0 and math.isfinite(temperature)):
        raise ValueError(f"temperature must be a finite number >= 0 (the experts' "
                         f"temperature; 0 for optimal experts), got {temperature!r}.")
    if not 0.0 < min_probability <= 1.0:
        raise ValueError(f"min_probability must lie in (0, 1], got {min_probability!r}.")
    shards = _shards(demonstrations, model)
    p0 = joint_initial_distribution(model, initial_distribution)
    _check_starts(shards, p0, model)
    scope = (torch.ones(features.dim, dtype=torch.bool) if only is None
             else as_mask(only, features.dim, "only"))

    t0 = time.perf_counter()
    pos = Positive(features)  # per-feature facts, once for every candidate
    demonstrated = _accrued(features, shards, p0, model, pos.state)
    if also_demonstrated is not None:
        demonstrated |= as_mask(also_demonstrated, features.dim, "also_demonstrated")
    unseen = ~demonstrated  # U
    probability = torch.full((features.dim,), math.nan, dtype=torch.float64)
    infeasible = torch.zeros(features.dim, dtype=torch.bool)
    candidates = torch.nonzero(unseen & scope).flatten().tolist()
    steps = candidates
    if progress:
        from tqdm.auto import tqdm
        steps = tqdm(candidates, desc="identifiability", leave=False)
    support = p0 > 0
    starts = torch.nonzero(support)  # [K, N] the joint states P0 gives mass to
    d0 = p0.reshape(-1).to(solver.device)
    masks = AllButOne(features, unseen, pos, model)
    chain = Chain(model, solver.device)
    hard_solver = candidate_solver(solver)
    overlaps = pos.overlaps() if open_overlaps else None

    def accrual(j: int, rivals: torch.Tensor | None = None) -> float | None:
        """P(experts accrue φ_j) with U \\ {j} forbidden (``open_overlaps``: outside
        j's support, and ``rivals`` inside it too); None: infeasible."""
        mask, terminal = masks(j, open_overlaps, rivals)
        if temperature == 0.0:  # on the cells U \\ {j} leaves open
            sol = solve_hard(hard_solver, reward + mask, terminal)
            feasible = torch.isfinite(sol.start_values(starts)).all()
        else:
            sol = solver.solve(reward + mask, temperature=temperature, forward=False,
                               terminal_value=terminal)
            feasible = torch.isfinite(sol.V[0].cpu()[support]).all()
        if not feasible:
            return None
        target = torch.zeros(features.dim, dtype=torch.bool)
        target[j] = True
        return killed_forward(
            sol, Hits(features, target, model, solver.device, last_move, pos), d0, chain)

    for j in steps:
        p = accrual(j)
        if p is None:
            infeasible[j] = True
        else:
            probability[j] = p
    n_solves = len(candidates)
    if overlaps is not None:
        # A required feature overlapping narrower required ones, asked again with them
        # forbidden inside its support too, narrowest first: kept only if still
        # accrued, i.e. if it forbids more than the narrower ones do.
        required = unseen & scope & (probability >= min_probability)
        width = pos.local.flatten(0, 2).sum(0)  # pairs (and joint states) where positive
        if pos.joint is not None:
            width = width.index_add(0, features.joint_columns, pos.joint.sum(0))
        for j in sorted(torch.nonzero(required).flatten().tolist(),
                        key=lambda k: (int(width[k]), k)):
            rivals = overlaps[j] & required & (width < width[j])
            if not rivals.any():
                continue
            p = accrual(j, rivals)
            n_solves += 1
            if p is None or p < min_probability:
                required[j] = False
                probability[j] = math.nan if p is None else p
    seconds = time.perf_counter() - t0
    required = unseen & scope & (probability >= min_probability)
    return Identifiability(
        names=names, scope=scope, demonstrated=demonstrated & scope, required=required,
        undetermined=unseen & scope & ~required, probability=probability,
        infeasible=infeasible, min_probability=float(min_probability),
        temperature=float(temperature), seconds=seconds, n_solves=n_solves,
        accrued=demonstrated)


# ------------------------------------------------------------------------ certificate
def certify_constraints(*, solver: FactoredSoftBellman, reward: FactoredReward,
                        cost_basis: FeatureBasis | FactoredFeatures,
                        demonstrations: Demonstrations | Sequence[Demonstrations],
                        temperature: float = CERTIFICATE_TEMPERATURE,
                        min_probability: float = CERTIFICATE_MIN_PROBABILITY,
                        initial_distribution=None, also_demonstrated=None,
                        other_rewards: Sequence[FactoredReward] = (),
                        progress: bool = False) -> Identifiability:
    """A learner's constraint set from what it holds: the "required" test of
    :func:`classify_features` asked of the learner's own model (docs/design.md §6).

    A certified feature ``j`` is one the learner's demonstrations (and P0) never accrue,
    and that experts optimal for the learned reward would still accrue with probability
    ``>= min_probability`` per trajectory if ``j`` alone were allowed and every other
    unseen feature forbidden: within the learner's model the data rule ``j`` out, whatever
    the undemonstrated rest is. No ground truth enters: the reward is the learner's
    ``ω_r · φ_r`` (its λ ω_c term left out: the constraints are what is being decided),
    the demonstrations its own shard, the dynamics and P0 the nominal model's.

    Differences from the evaluation's classification, each for a reason:

    - ``temperature`` 0: the learners' model is maximum-causal-entropy at temperature 1,
      but on optimal demonstrations the scale of the learned ω_r grows without bound
      (docs/design.md §6, RFD), so the learned policy tends to the hard max: temperature
      0 is that limit, and at temperature 1 softly reachable cells beside the route
      (next to a start, say) would be certified too.
    - ``min_probability`` 1e-3, ten times below the evaluation's 0.01: the learned reward
      is an estimate, and a required feature near the evaluation's threshold (a slip-only
      shortcut) can fall below it under the estimate (measured in docs/experiments.md).
    - ``also_demonstrated``: the features the *other* learners' demonstrations accrue
      (exchanged once as a bitmask, :meth:`~dicrl_torch.algos.dicrl.DICRL.network_or`).
      The experts are the same team for every learner, so with budget 0 a feature any shard
      accrues is no constraint: it is neither certified nor forbidden while another is
      tested. Without it a shard of 10 trajectories that happened never to take a route
      the experts take half the time (a tie) finds that route required.
    - ``other_rewards``: further rewards the data support as well as ``reward`` (the other
      learners' η̄: every learner estimates the same experts' reward). A feature is
      certified only if experts optimal for *each* of them accrue it; its probability is
      the smallest. Optimal demonstrations pin the reward's direction only loosely, and
      a route one estimate ranks first and another second is not something the data
      require. Only the features ``reward`` certifies are solved again.
    - ``last_move`` False: at the last decision nothing more is scored, so optimal experts
      pick any safe move, uniformly; whether a shard of m trajectories shows a given last
      move is chance ((1 - 1/k)^m), not preference. Neither the action at ``t = T-1`` nor
      the state ``s_T`` accrues (a learner with 10 or 20 trajectories would otherwise
      certify the moves and cells beside its goals that it happened never to see).

    Args:
        solver: the factored solver of the learners' nominal model.
        reward: the learned reward, ``reward_basis().weighted(η̄[:-1])``.
        cost_basis, demonstrations, initial_distribution: as :func:`classify_features`;
            the demonstrations are the learner's own.
        also_demonstrated: ``[l]`` bool, the features the other learners' shards accrue
            (above); None: the learner's own shard alone decides.
        other_rewards: rewards each certified feature must also be required under
            (above); none: ``reward``'s certificate.
        temperature, min_probability: the certificate's (above).
        progress: a tqdm bar over the candidates.

    Returns:
        The classification of every feature; its ``required`` mask ``[l]`` is the
        certified set and ``probability`` the certificate's probabilities.
    """
    def classify(r, only=None) -> Identifiability:
        # one bar, over the first reward's candidates: the re-checks are a few solves
        return classify_features(solver=solver, reward=r, cost_basis=cost_basis,
                                 demonstrations=demonstrations, temperature=temperature,
                                 initial_distribution=initial_distribution, only=only,
                                 min_probability=min_probability, last_move=False,
                                 also_demonstrated=also_demonstrated, open_overlaps=True,
                                 progress=progress and only is None)

    cert = classify(reward)
    for other in other_rewards:
        if not cert.required.any():
            break
        alt = classify(other, only=cert.required)
        asked = cert.required
        required = asked & alt.required
        probability = torch.where(asked, torch.fmin(cert.probability, alt.probability),
                                  cert.probability)
        cert = replace(cert, required=required,
                       undetermined=cert.undetermined | (asked & ~required),
                       probability=probability, seconds=cert.seconds + alt.seconds,
                       n_solves=cert.n_solves + alt.n_solves)
    return cert


def demonstrated_mask(*, cost_basis: FeatureBasis | FactoredFeatures, model: TabularGridModel,
                      demonstrations: Demonstrations | Sequence[Demonstrations],
                      initial_distribution=None) -> torch.Tensor:
    """``[l]`` bool: the features ``demonstrations`` (or P0) accrue, the "demonstrated"
    class of :func:`classify_features` without a solve: what a learner's shard tells the
    others about which features cannot be constraints."""
    features, _ = _features_of(cost_basis, model)
    p0 = joint_initial_distribution(model, initial_distribution)
    return _accrued(features, _shards(demonstrations, model), p0, model,
                    is_state_feature(features))


# ------------------------------------------------------------------------ checks
def check_indicator_basis(cost_basis, model: TabularGridModel) -> None:
    """Raise the error :func:`classify_features` and :func:`certify_constraints` would
    raise for ``cost_basis`` (another model's, negative, or positive everywhere), before
    anything is trained."""
    _features_of(cost_basis, model)


def _features_of(cost_basis, model: TabularGridModel) -> tuple[FactoredFeatures, list[str]]:
    features, names = cost_features_of(cost_basis, model)
    if features.local.min() < 0 or (features.joint is not None and features.joint.min() < 0):
        raise ValueError("The cost features must be non-negative: a feature is accrued "
                         "where it is positive. Use an indicator basis (shared, per_expert, "
                         "regions) or features with exact zeros (local_relu_grid).")
    # φ_j(s, a) >= Σ_i min local_i + min joint: positive everywhere when that is.
    floor = features.local.amin(dim=(1, 2)).sum(0)
    if features.joint is not None:
        floor = floor.index_add(0, features.joint_columns, features.joint.amin(0))
    everywhere = floor > 0
    if everywhere.any():
        bad = [names[j] for j in torch.nonzero(everywhere).flatten().tolist()]
        shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        raise ValueError(
            f"{len(bad)} cost feature(s) are positive on every state-action pair ({shown}), "
            f"so every trajectory accrues them and identifiability says nothing about them "
            f"(e.g. a frozen random MLP basis: a sigmoid is positive everywhere). Use features "
            f"with exact zeros: features/cost=local_relu_grid (GridLocalReLUBasis), an "
            f"indicator basis (shared, per_expert, regions), or end your network with a ReLU "
            f"clipped to max_value.")
    return features, names


def _shards(demonstrations, model: TabularGridModel) -> list[Demonstrations]:
    shards = [demonstrations] if isinstance(demonstrations, Demonstrations) else \
        list(demonstrations) if isinstance(demonstrations, Sequence) else None
    if shards is None:
        raise TypeError(f"demonstrations must be a Demonstrations or a sequence of them, "
                        f"got {type(demonstrations).__name__}.")
    if not shards:
        raise ValueError("No demonstrations given: pass at least one set (all the "
                         "learners' shards together).")
    for k, demos in enumerate(shards):
        if not isinstance(demos, Demonstrations):
            raise TypeError(f"demonstrations[{k}] is a {type(demos).__name__}, not a "
                            f"Demonstrations.")
        found = (demos.n_experts, demos.n_cells, demos.n_actions, demos.horizon)
        want = (model.n_experts, model.n_cells, model.n_actions, model.horizon)
        if found != want:
            raise ValueError(
                f"Demonstrations set {k} has {demos.n_experts} experts on {demos.n_cells} "
                f"cells with {demos.n_actions} actions over T={demos.horizon}; the solver's "
                f"model has {model.n_experts} experts, {model.n_cells} cells, "
                f"{model.n_actions} actions, T={model.horizon}. Sample them from this "
                f"model (or build the model of the grid they come from).")
        if demos.n_trajectories == 0:  # pragma: no cover - Demonstrations refuses it
            raise ValueError(f"Demonstrations set {k} is empty.")
    return shards


def _check_starts(shards: list[Demonstrations], p0: torch.Tensor,
                  model: TabularGridModel) -> None:
    flat = p0.reshape(-1)
    for k, demos in enumerate(shards):
        starts = encode_joint(torch.from_numpy(demos.states[:, 0].copy()), model.n_cells)
        off = flat[starts] <= 0
        if off.any():
            i = int(torch.nonzero(off)[0])
            cells = [model.layout.xy(int(c)) for c in demos.states[i, 0]]
            raise ValueError(
                f"Demonstration {i} of set {k} starts at {cells}, where P0 has no mass; "
                f"pass initial_distribution= the P0 the demonstrations were sampled from.")


def _accrued(features: FactoredFeatures, shards: list[Demonstrations], p0: torch.Tensor,
             model: TabularGridModel, state_features: torch.Tensor) -> torch.Tensor:
    """``[l]`` bool: the "demonstrated" class, features some shard or P0 accrues."""
    seen = _p0_features(features, p0, model, state_features)
    for demos in shards:
        seen |= demonstrated_features(features, demos, model.gamma,
                                      state_features=state_features)
    return seen


def _p0_features(features: FactoredFeatures, p0: torch.Tensor, model: TabularGridModel,
                 state_features: torch.Tensor | None = None) -> torch.Tensor:
    """``[l]`` bool: state features positive on some state where P0 has mass
    (``state_features``: ``is_state_feature(features)`` if already known)."""
    flat = torch.nonzero(p0.reshape(-1) > 0).flatten()
    cells = decode_joint(flat, model.n_cells, model.n_experts)  # [K, N]
    seen = torch.zeros(features.dim, dtype=torch.bool)
    for chunk in cells.split(CHUNK_STATES * 16):
        phi = features.at(chunk, torch.zeros_like(chunk), model.n_cells)  # [K, l]
        seen |= (phi > 0).any(0)
    return seen & (is_state_feature(features) if state_features is None else state_features)
