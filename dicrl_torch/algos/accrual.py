"""The probability that a policy accrues a cost feature, computed exactly, and the
machinery the identifiability classification shares between its candidates
(:mod:`dicrl_torch.algos.identifiability`).

**The probability of accruing a feature** (:func:`accrual_probability`) is not its
expected (discounted) count: it is ``P(∃ t < T: φ_j(s_t, a_t) > 0, or φ_j(s_T) > 0 for a
state feature)`` under the policy and the nominal dynamics, computed exactly by a
forward pass on the chain in which the mass that accrues ``φ_j`` is removed at the step
it does so (the removed mass, summed, is the probability). The chain is kept sparse:
only joint states that still carry mass are visited, and the policy is read there with
:meth:`~dicrl_torch.solvers.factored.SoftBellmanSolution.policy_at` — the very policy
:func:`~dicrl_torch.solvers.experts.sample_trajectories` samples from (hard max with
uniform ties at temperature 0, soft-optimal above). With optimal experts from a few start
states the support stays small, so a candidate costs about one backward solve. Joint
features (the collision) are removed on the joint state like any other.
"""

from __future__ import annotations

import itertools
import math
import weakref

import numpy as np
import torch

from dicrl_torch.algos.greedy import cells_or_joint, is_state_feature
from dicrl_torch.envs.grid import TabularGridModel, decode_joint
from dicrl_torch.features.bases import FactoredFeatures, FactoredReward, FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman, SoftBellmanSolution

__all__ = ["AllButOne", "Chain", "Hits", "Positive", "accrual_probability", "as_mask",
           "candidate_solver", "joint_initial_distribution", "killed_forward"]

# Joint states per policy query of the forward pass (bounds memory at 3 experts:
# a query holds [B, (1 + A1)^N] values).
CHUNK_STATES = 4096
# State-action pairs per chunk of an eager backward step of the classification's solves
# (see candidate_solver): 9 cells per chunk, the solver's default, leaves a one-expert
# step at 9 kernel calls of 81 pairs each, all overhead.
_CHUNK_PAIRS = 1 << 18
# Joint states up to which the forward pass decodes them from a table.
_DECODE_TABLE_STATES = 1 << 20


def as_mask(mask, l: int, name: str) -> torch.Tensor:
    if isinstance(mask, np.ndarray):
        mask = torch.as_tensor(np.array(mask))
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != (l,):
        got = (f"{tuple(mask.shape)} {mask.dtype}" if hasattr(mask, "shape")
               else type(mask).__name__)
        raise ValueError(f"{name} must be a [{l}] bool mask (tensor or array), got {got}.")
    return mask.cpu()


# ------------------------------------------------------------------------ P0
def joint_initial_distribution(model: TabularGridModel, p0=None) -> torch.Tensor:
    """P0 as a checked joint distribution ``[S1]*N`` float64.

    Args:
        model: the tabular model.
        p0: None (the model's own P0: a point mass on the start cells with fixed starts,
            the product of uniform start sets otherwise), a joint
            distribution ``[S1]*N``, or one start distribution per expert ``[N, S1]``
            (independent starts: their product).

    Raises:
        ValueError: another shape, negative or non-finite entries, or rows that do not
            sum to 1.
    """
    if p0 is None:
        return model.initial_distribution()
    N, S1 = model.n_experts, model.n_cells
    p = torch.as_tensor(p0, dtype=torch.float64).cpu()
    if not torch.isfinite(p).all() or (p < 0).any():
        raise ValueError("initial_distribution must hold finite non-negative probabilities.")
    if tuple(p.shape) == model.state_shape:
        joint = p
    elif tuple(p.shape) == (N, S1):
        joint = p[0]
        for i in range(1, N):
            joint = joint.unsqueeze(-1) * p[i]
        bad = [i for i in range(N) if abs(float(p[i].sum()) - 1.0) > 1e-9]
        if bad:
            raise ValueError(f"initial_distribution [N, S1]: the start distributions of "
                             f"experts {bad} do not sum to 1; normalise each row.")
    else:
        raise ValueError(f"initial_distribution must be a joint distribution of shape "
                         f"{model.state_shape} or one per expert of shape {(N, S1)}, got "
                         f"{tuple(p.shape)}.")
    if abs(float(joint.sum()) - 1.0) > 1e-9:
        raise ValueError(f"initial_distribution sums to {float(joint.sum()):.6g}, not 1; "
                         f"normalise it.")
    return joint


class Hits:
    """Where a set of features is positive: per expert ``[N, S1, A1]``, on joint states
    ``[S]`` (joint part), and on final states ``[S]`` (its state features); and what
    counts at the last decision ``t = T-1`` (``last_local``, ``last_joint``).

    Without ``last_move`` the last move counts for nothing: neither the action taken at
    ``t = T-1`` nor the state ``s_T`` it leads to accrues (the state ``s_{T-1}``, reached by
    a scored move, still does).

    ``tables`` (a :class:`Positive` of ``features``) saves the passes over the features
    when many targets are asked of the same ones."""

    def __init__(self, features: FactoredFeatures, target: torch.Tensor,
                 model: TabularGridModel, device: torch.device,
                 last_move: bool = True, tables: Positive | None = None) -> None:
        N, S1, A1 = model.n_experts, model.n_cells, model.n_actions
        pos = Positive(features) if tables is None else tables
        self.local = pos.local[..., target].any(-1).to(device)  # [N, S1, A1]
        self.joint = None
        state = target & pos.state
        cell = pos.cell[..., state].any(-1)  # [N, S1]
        joint_state = None
        if features.joint is not None:
            cols = target[features.joint_columns]
            if cols.any():
                self.joint = pos.joint[:, cols].any(-1).to(device)  # [S]
            cols = state[features.joint_columns]
            if cols.any():
                joint_state = pos.joint[:, cols].any(-1)
        if last_move:
            self.final = cells_or_joint(cell, joint_state, model).reshape(-1).to(device)
            self.last_local, self.last_joint = self.local, self.joint
        else:
            self.final = torch.zeros(model.n_states, dtype=torch.bool, device=device)
            self.last_local = cell.unsqueeze(-1).expand(N, S1, A1).to(device)
            self.last_joint = None if joint_state is None else joint_state.to(device)
        # Whether each part can accrue at all (the forward pass skips the others).
        self.any_final = bool(self.final.any())
        self.experts = [i for i in range(N) if bool(self.local[i].any())]
        self.last_experts = [i for i in range(N) if bool(self.last_local[i].any())]


class Positive:
    """Per-feature facts every mask and every target of a classification reads: where
    each feature is positive (``local [N, S1, A1, l]``, ``cell [N, S1, l]`` at the first
    action (a state feature's value), ``joint [S, lj]``) and which features are state
    features (``state [l]``). One pass over the features per classification."""

    def __init__(self, features: FactoredFeatures,
                 state_features: torch.Tensor | None = None) -> None:
        self.local = features.local > 0
        self.cell = self.local[:, :, 0]
        self.joint = None if features.joint is None else features.joint > 0
        self._joint_columns = features.joint_columns
        self.state = is_state_feature(features) if state_features is None else state_features

    def overlaps(self) -> torch.Tensor:
        """``[l, l]`` bool: features of one kind whose supports meet: two state features
        positive on a common cell of an expert, two features of the moves positive on a
        common state-action pair, two joint features positive on a common joint state
        (every feature overlaps itself where it is positive somewhere). Indicator bases
        have none but themselves: their cells, moves and collision are disjoint."""
        N, S1, A1, l = self.local.shape
        cells = self.cell.reshape(N * S1, l).to(torch.float64)
        pairs = self.local.reshape(N * S1 * A1, l).to(torch.float64)
        state = self.state
        out = ((cells.T @ cells) > 0) & state[:, None] & state[None, :]
        moves = ~state & self.local.flatten(0, 2).any(0)
        out |= ((pairs.T @ pairs) > 0) & moves[:, None] & moves[None, :]
        if self.joint is not None:
            joint = self.joint.to(torch.float64)
            cols = self._joint_columns
            out[cols[:, None], cols[None, :]] |= (joint.T @ joint) > 0
        return out


class AllButOne:
    """The hard masks of ``U \\ {j}`` for the features ``j`` of ``U``, exactly as
    :func:`~dicrl_torch.algos.greedy.constraint_masks` builds them, from counts of the
    features of ``U`` positive at each pair, cell and joint state: one pass over the
    features for all candidates instead of one per candidate.

    With ``open_support`` the mask leaves ``j``'s whole support open to features of its
    kind (:meth:`Positive.overlaps`): a pair where ``j`` is positive is forbidden only by
    a feature of another kind (a move inside a cell), so a unit nested in a wider one is
    asked whether its own support is needed. Indicator bases have no two features of one
    kind positive at one pair, and get the same masks either way."""

    def __init__(self, features: FactoredFeatures, unseen: torch.Tensor, pos: Positive,
                 model: TabularGridModel) -> None:
        self.features, self.unseen, self.pos, self.model = features, unseen, pos, model
        self.count = pos.local[..., unseen].sum(-1)  # [N, S1, A1]
        self.state_count = pos.local[..., unseen & pos.state].sum(-1)  # [N, S1, A1]
        self.cell_count = pos.cell[..., unseen & pos.state].sum(-1)  # [N, S1]
        self.joint_count = None
        if features.joint is not None:
            self.joint_count = pos.joint[:, unseen[features.joint_columns]].sum(-1)  # [S]

    def __call__(self, j: int, open_support: bool = False,
                 rivals: torch.Tensor | None = None
                 ) -> tuple[FactoredReward, torch.Tensor | None]:
        """``(mask, terminal)`` of ``U \\ {j}`` (``j`` in ``U``); with ``open_support``,
        of ``U`` outside ``j``'s support for its kind (class docstring); ``rivals``
        ``[l]`` bool: features forbidden everywhere, inside ``j``'s support too."""
        features, pos, model = self.features, self.pos, self.model
        others = self.unseen.clone()
        others[j] = False
        mine = pos.local[..., j]  # [N, S1, A1]
        if open_support:
            state = bool(pos.state[j])
            kin = self.state_count if state else self.count - self.state_count
            hit = ((self.count - kin) > 0) | (((kin - mine.long()) > 0) & ~mine)
        else:
            hit = (self.count - mine.long()) > 0  # [N, S1, A1]
        if rivals is not None:
            others |= rivals
            hit = hit | pos.local[..., rivals].any(-1)
        local = torch.zeros(hit.shape, dtype=torch.float64).masked_fill(hit, -math.inf)
        joint = joint_hit = None
        if features.joint is not None and others[features.joint_columns].any():
            cols = features.joint_columns
            mine_joint = pos.joint[:, cols == j].any(-1)  # [S]
            count = self.joint_count - mine_joint.long()
            joint_hit = (count > 0) & ~mine_joint if open_support else count > 0
            if rivals is not None and rivals[cols].any():
                joint_hit = joint_hit | pos.joint[:, rivals[cols]].any(-1)
            joint = torch.zeros(joint_hit.shape, dtype=torch.float64).masked_fill(
                joint_hit, -math.inf)
        mask = FactoredReward(local=local, joint=joint)
        if not (others & pos.state).any():
            return mask, None
        mine_cell = pos.cell[..., j] if pos.state[j] else torch.zeros_like(pos.cell[..., 0])
        bad = (self.cell_count - mine_cell.long()) > 0
        if open_support:
            bad = bad & ~mine_cell
        if rivals is not None:
            bad = bad | pos.cell[..., rivals & pos.state].any(-1)
        bad = cells_or_joint(bad, joint_hit, model)
        return mask, torch.zeros(model.state_shape, dtype=torch.float64).masked_fill(
            bad, -math.inf)


def accrual_probability(solution: SoftBellmanSolution, features: FactoredFeatures | FeatureBasis,
                        target, initial_distribution=None, last_move: bool = True) -> float:
    """``P(a trajectory accrues some feature of target)`` under the solution's policy.

    A trajectory accrues ``φ_j`` when ``φ_j(s_t, a_t) > 0`` at some ``t < T`` or, for a
    state feature, ``φ_j(s_T) > 0``. Exact: the forward pass of the chain that drops
    the mass accruing ``target`` at the step it does so (module docstring), with the
    policy of ``solution.policy_at`` and the model's nominal dynamics.

    Args:
        solution: a solve of the model (any temperature, with or without forward pass).
        features: the cost features (or their basis).
        target: ``[l]`` bool, the features whose first accrual ends a trajectory's
            survival, or an int (one feature).
        initial_distribution: P0 (see :func:`joint_initial_distribution`); default
            the model's.
        last_move: whether the last move accrues: the action at ``t = T-1`` and a state
            feature positive at ``s_T`` (the true CMG's semantics). False: neither (the
            certificate's: optimal experts are indifferent among safe last moves).
    """
    features = features() if isinstance(features, FeatureBasis) else features
    if isinstance(target, int):
        j = target
        target = torch.zeros(features.dim, dtype=torch.bool)
        target[j] = True
    target = as_mask(target, features.dim, "target")
    solver = solution.solver
    model = solver.model
    hits = Hits(features, target, model, solver.device, last_move)
    d = joint_initial_distribution(model, initial_distribution).reshape(-1).to(solver.device)
    return killed_forward(solution, hits, d)


class Chain:
    """The model's tables every forward pass of a classification reads: each expert's
    move targets and its own cell as offsets of the flattened joint state, and the
    move/stay patterns of the experts with their probabilities."""

    def __init__(self, model: TabularGridModel, device: torch.device) -> None:
        N, S1, p = model.n_experts, model.n_cells, model.p_success
        self.model, self.device = model, device
        powers = [S1 ** (N - 1 - i) for i in range(N)]
        nxt = model.next_cell.to(device)  # [S1, A1]
        self.move = [nxt * powers[i] for i in range(N)]  # [S1, A1]
        self.stay = [torch.arange(S1, device=device) * powers[i] for i in range(N)]  # [S1]
        patterns = [(m, p ** sum(m) * (1.0 - p) ** (N - sum(m)))
                    for m in itertools.product((False, True), repeat=N)]
        self.patterns = [(m, w, tuple(1 + i for i in range(N) if not m[i]))
                         for m, w in patterns if w > 0.0]
        # Joint state -> cells, as a table where it is small (3 experts: 12 MB).
        self.cells = (decode_joint(torch.arange(model.n_states, device=device), S1, N)
                      if model.n_states <= _DECODE_TABLE_STATES else None)

    def decode(self, flat: torch.Tensor) -> torch.Tensor:
        """Cells ``[B, N]`` of joint states ``flat`` ``[B]``."""
        if self.cells is None:
            return decode_joint(flat, self.model.n_cells, self.model.n_experts)
        return self.cells[flat]


def killed_forward(solution: SoftBellmanSolution, hits: Hits, d: torch.Tensor,
                    chain: Chain | None = None) -> float:
    model = solution.solver.model
    N, A1, T = model.n_experts, model.n_actions, model.horizon
    device = d.device
    if chain is None:
        chain = Chain(model, device)
    removed = torch.zeros((), dtype=torch.float64, device=device)
    lone = [1] * N

    def axis(x: torch.Tensor, i: int) -> torch.Tensor:  # [B, A1] -> expert i's action axis
        shape = [x.shape[0]] + lone
        shape[1 + i] = A1
        return x.reshape(shape)

    for t in range(T):
        support = torch.nonzero(d > 0).flatten()
        if support.numel() == 0:  # every trajectory has accrued it
            return float(removed)
        d_next = torch.zeros_like(d)
        last = t == T - 1
        local, joint = (hits.last_local, hits.last_joint) if last else (hits.local, hits.joint)
        experts = hits.last_experts if last else hits.experts
        for flat in support.split(CHUNK_STATES):
            B = flat.shape[0]
            cells = chain.decode(flat)  # [B, N]
            mass = d[flat]
            pi = solution.policy_at(t, cells).to(device, torch.float64)  # [B, A1^N]
            rho = (mass.unsqueeze(1) * pi).reshape([B] + [A1] * N)
            # The mass that accrues now leaves the chain. (Where nothing here accrues,
            # the removed sum is 0 and the fill a no-op: both skipped.)
            acc = None
            for i in experts:
                part = axis(local[i, cells[:, i]], i)
                acc = part if acc is None else acc | part
            if joint is not None:
                part = joint[flat].reshape([B] + lone)
                acc = part if acc is None else acc | part
            if acc is not None and bool(acc.any()):
                acc = acc.expand_as(rho)
                removed += rho[acc].sum()
                rho = rho.masked_fill(acc, 0.0)
            # Each expert's part of the flattened joint state it lands on, if it moves
            # (per action) and if it stays.
            to = [(axis(chain.move[i][cells[:, i]], i),
                   chain.stay[i][cells[:, i]].reshape([B] + lone)) for i in range(N)]
            for moves, w, stay_axes in chain.patterns:
                r = rho.sum(stay_axes, keepdim=True) if stay_axes else rho
                target = to[0][0 if moves[0] else 1]
                for i in range(1, N):
                    target = target + to[i][0 if moves[i] else 1]
                target = target.expand_as(r)
                d_next.index_add_(0, target.reshape(-1), (w * r).reshape(-1))
        d = d_next
    if hits.any_final:
        removed += d[hits.final].sum()
    return float(removed)


# Eager solvers with wider chunks, one per solver the classification was asked of.
_WIDE_SOLVERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def candidate_solver(solver: FactoredSoftBellman) -> FactoredSoftBellman:
    """The solver the classification's hard-max (temperature 0) solves run on: ``solver``
    itself, or — for an eager solver whose chunks of expert-1 cells are small against
    ``_CHUNK_PAIRS`` — a twin with wider chunks. The chunk only splits the backward step
    over cells, and the hard step is elementwise arithmetic and maxima, computed alike in
    any chunk: the values are the same, bit for bit (not so the soft step, whose sums
    over actions may round differently in another chunk width). A one-expert step
    becomes one kernel call instead of nine."""
    if type(solver) is not FactoredSoftBellman or solver.use_compile:
        return solver
    m = solver.model
    per_cell = m.n_actions ** m.n_experts * m.n_cells ** (m.n_experts - 1)
    widest = _CHUNK_PAIRS // per_cell
    if widest <= solver.chunk_cells:
        return solver
    n_chunks = -(-m.n_cells // widest)
    chunk = -(-m.n_cells // n_chunks)  # as even as they come: 81 cells, 2 experts: 3 x 27
    if chunk <= solver.chunk_cells:
        return solver
    twin = _WIDE_SOLVERS.get(solver)
    if twin is None or twin.chunk_cells != chunk or twin.model is not m \
            or twin.device != solver.device or twin.dtype != solver.dtype:
        twin = FactoredSoftBellman(model=m, device=solver.device, dtype=solver.dtype,
                                   compile=False, chunk_cells=chunk)
        _WIDE_SOLVERS[solver] = twin
    twin.progress = solver.progress
    # Its float32 scale warning only where the solver's own would be new (the level the
    # solver last warned at, where it keeps one).
    if hasattr(solver, "_warned_value") and hasattr(twin, "_warned_value"):
        twin._warned_value = max(twin._warned_value, solver._warned_value)
    return twin

