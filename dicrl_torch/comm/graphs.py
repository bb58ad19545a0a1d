"""Communication graphs of the learners and checks of the paper's Assumptions 1–3.

The inner (fast) loop mixes with ``W(k)`` over time-varying directed graphs
``G(k) = (V, E(k))``; the outer (slow) loop mixes with ``W̄(n)``. Convention of the
paper (Section 2): ``W[v, v'] > 0`` iff learner ``v`` receives from learner ``v'``
(the edge ``(v, v') ∈ E(k)``), and every learner always hears itself.

- Assumption 1 (B-strong connectivity): the union ``E(k) ∪ … ∪ E(k+B-1)`` is strongly
  connected for every ``k``.
- Assumption 2 (i) ``W(k)`` is doubly stochastic; (ii) non-degenerate: every diagonal
  entry and every positive entry is ``≥ ε`` for one ``ε ∈ (0, 1]``.
- Assumption 3: ``W̄(n)`` is complete (every learner hears every other at every outer
  step), doubly stochastic and non-degenerate.

All provided schedules are built as ``s·I + (1 - s)/m · Σ_j P_j`` with permutation
matrices ``P_j``: a convex combination of permutations is doubly stochastic by
construction (Birkhoff), and its positive entries are bounded below by a constant.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np
import torch

__all__ = [
    "CompleteSchedule", "DirectedCycleSchedule", "GraphAssumptionError", "LinkFailures",
    "MatrixSchedule", "MixingSchedule", "RingSchedule", "TimeVaryingSchedule",
    "check_inner_schedule", "check_outer_schedule", "strongly_connected",
]

_MAX_LISTED = 8  # entries quoted in an error message before "…"


class GraphAssumptionError(ValueError):
    """A mixing schedule breaks one of the paper's Assumptions 1–3."""


# ---------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)


def _check_self_weight(value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 < value < 1.0:
        raise ValueError(
            f"self_weight must be a float in (0, 1), got {value!r}: 0 would drop the learner's "
            "own estimate (Assumption 2(ii)) and 1 would stop all communication (Assumption 1)."
        )
    return float(value)


def _permutation_mixing(senders: Sequence[np.ndarray], self_weight: float) -> torch.Tensor:
    """Doubly stochastic mixing matrix from permutations.

    Args:
        senders: ``m`` permutations of ``range(N)``, each ``[N]``; ``senders[j][v]`` is the
            learner that ``v`` receives from through ``P_j``.
        self_weight: ``s ∈ (0, 1)``, the weight on ``I``.

    Returns:
        ``W = s·I + (1 - s)/m · Σ_j P_j`` with ``P_j[v, senders[j][v]] = 1``, ``[N, N]``
        float64. Fixed points of a permutation simply add to the diagonal.
    """
    n = len(senders[0])
    w = torch.eye(n, dtype=torch.float64) * self_weight
    rows = torch.arange(n)
    for perm in senders:
        w[rows, torch.as_tensor(perm, dtype=torch.long)] += (1.0 - self_weight) / len(senders)
    return w


def _fmt_entries(idx: np.ndarray, values: np.ndarray | None = None) -> str:
    """``[(v, v') = w, …]`` for the first few offending entries."""
    items = [
        f"({int(i)}, {int(j)})" + ("" if values is None else f" = {values[i, j]:.3g}")
        for i, j in idx[:_MAX_LISTED]
    ]
    more = f", … ({len(idx) - _MAX_LISTED} more)" if len(idx) > _MAX_LISTED else ""
    return "[" + ", ".join(items) + more + "]"


# ---------------------------------------------------------------------------
# schedules
# ---------------------------------------------------------------------------


class MixingSchedule:
    """Sequence of mixing matrices ``W(k)``, ``k = 0, 1, …``.

    Subclasses set ``n_learners`` and ``period`` and implement ``_matrix(k)``. ``W(k)``
    must depend only on the constructor arguments and ``k`` (no global RNG), so that
    every learner can evaluate the same schedule locally.

    Attributes:
        n_learners: number of learners ``N_L``.
        period: the ``B`` of Assumption 1 for which the schedule guarantees that the
            union graph over any ``B`` consecutive steps is strongly connected.
    """

    n_learners: int
    period: int

    def _matrix(self, k: int) -> torch.Tensor:
        raise NotImplementedError

    def __call__(self, k: int) -> torch.Tensor:
        """Mixing matrix at step ``k``.

        Args:
            k: step index, ``k >= 0``.

        Returns:
            ``W(k)``, ``[N_L, N_L]`` float64, ``W[v, v'] > 0`` iff ``v`` receives from ``v'``.
            A fresh copy: callers may modify it.
        """
        k = _check_int("k", k, 0)
        return torch.as_tensor(self._matrix(k), dtype=torch.float64).clone()

    def edges(self, k: int) -> list[tuple[int, int]]:
        """Communication links at step ``k`` as ``(receiver, sender)``, self-loops excluded."""
        w = self(k)
        w.fill_diagonal_(0.0)
        return [(int(v), int(u)) for v, u in torch.nonzero(w > 0).tolist()]

    def neighbors(self, v: int, k: int) -> list[int]:
        """Learners ``v' != v`` that learner ``v`` receives from at step ``k`` (ascending)."""
        v = _check_int("v", v, 0)
        if v >= self.n_learners:
            raise ValueError(f"learner index v must be in [0, {self.n_learners}), got {v}.")
        row = self(k)[v]
        return [int(u) for u in torch.nonzero(row > 0).flatten().tolist() if u != v]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_learners={self.n_learners}, period={self.period})"


class _CyclicSchedule(MixingSchedule):
    """Schedule cycling through a fixed tuple of matrices: ``W(k) = cycle[k % len(cycle)]``.

    Every provided schedule is of this form, so ``W(k)`` is computed once per residue.
    """

    def __init__(self, cycle: Sequence[torch.Tensor], period: int) -> None:
        self._cycle = tuple(cycle)
        self.period = period

    def _matrix(self, k: int) -> torch.Tensor:
        return self._cycle[k % len(self._cycle)]


class CompleteSchedule(_CyclicSchedule):
    """Complete graph with uniform weights: ``W = 1/N`` everywhere (period 1).

    Satisfies Assumption 3, hence usable for the outer loop, and is the fastest
    mixing matrix possible (exact averaging in one step).
    """

    def __init__(self, *, n_learners: int) -> None:
        self.n_learners = _check_int("n_learners", n_learners, 1)
        n = self.n_learners
        super().__init__([torch.full((n, n), 1.0 / n, dtype=torch.float64)], period=1)


class RingSchedule(_CyclicSchedule):
    """Undirected ring: learner ``v`` mixes with ``v ± 1 (mod N)`` (period 1).

    ``W = s·I + (1 - s)/2 · (P + Pᵀ)`` with ``P`` the cyclic shift, i.e. ``s`` on the
    diagonal and ``(1 - s)/2`` to each neighbour: symmetric, doubly stochastic. For
    ``N = 2`` both neighbours coincide (``W = [[s, 1-s], [1-s, s]]``); for ``N = 1``
    ``W = [[1]]``.

    Args:
        n_learners: ``N >= 1``.
        self_weight: ``s ∈ (0, 1)``; the default 1/3 weighs self and both neighbours equally.
    """

    def __init__(self, *, n_learners: int, self_weight: float = 1.0 / 3.0) -> None:
        self.n_learners = _check_int("n_learners", n_learners, 1)
        self.self_weight = _check_self_weight(self_weight)
        v = np.arange(self.n_learners)
        senders = [(v - 1) % self.n_learners, (v + 1) % self.n_learners]
        super().__init__([_permutation_mixing(senders, self.self_weight)], period=1)


class DirectedCycleSchedule(_CyclicSchedule):
    """Directed cycle: learner ``v`` receives from ``v - 1 (mod N)`` only (period 1).

    ``W = s·I + (1 - s)·P`` with ``P`` a cyclic permutation: doubly stochastic but not
    symmetric, the simplest strongly connected directed graph.

    Args:
        n_learners: ``N >= 1``.
        self_weight: ``s ∈ (0, 1)``.
    """

    def __init__(self, *, n_learners: int, self_weight: float = 0.5) -> None:
        self.n_learners = _check_int("n_learners", n_learners, 1)
        self.self_weight = _check_self_weight(self_weight)
        senders = [(np.arange(self.n_learners) - 1) % self.n_learners]
        super().__init__([_permutation_mixing(senders, self.self_weight)], period=1)


class TimeVaryingSchedule(_CyclicSchedule):
    """Time-varying directed graphs, strongly connected only over ``period`` steps.

    Construction: learners are put in a random order ``σ`` (drawn from ``seed``) and the
    path ``σ_0, …, σ_{N-1}`` is cut into ``m = min(B, N - 1)`` overlapping segments
    ``σ_{a_i}, …, σ_{a_{i+1}}`` (consecutive segments share one learner,
    ``0 = a_0 < … < a_m = N - 1``). At a step ``k`` with ``r = k mod B < m`` only
    segment ``r`` communicates, along the directed cycle through its learners (a swap
    for a two-learner segment); at ``r >= m`` (only when ``B > N - 1``) nobody
    communicates, ``W = I``. Each ``W(k) = s·I + (1 - s)·P_k`` with ``P_k`` a permutation,
    hence doubly stochastic.

    Guarantee: any ``B`` consecutive steps cover every residue mod ``B``, so their union
    contains every segment's cycle; the cycles are strongly connected and chained by
    shared learners, so the union is strongly connected (Assumption 1 with this ``B``).
    For ``N >= 3`` no single ``W(k)`` is strongly connected (a segment misses a learner),
    and ``B`` is tight: some window of ``B - 1`` steps misses a segment.

    Args:
        n_learners: ``N >= 1``.
        period: ``B``; ``>= 2`` when ``N >= 3`` (with ``B = 1`` use
            ``DirectedCycleSchedule``). ``B > N - 1`` slows mixing with idle steps.
        self_weight: ``s ∈ (0, 1)``.
        seed: seed of the learner order ``σ`` (``np.random.default_rng(seed)``).
    """

    def __init__(
        self, *, n_learners: int, period: int = 2, self_weight: float = 0.5, seed: int = 0
    ) -> None:
        self.n_learners = n = _check_int("n_learners", n_learners, 1)
        period = _check_int("period", period, 1)
        if n >= 3 and period < 2:
            raise ValueError(
                f"period={period} is too small for a time-varying schedule of {n} learners: "
                "a single permutation step that is strongly connected is a fixed cycle. Use "
                "period >= 2, or DirectedCycleSchedule for a static strongly connected graph."
            )
        self.self_weight = _check_self_weight(self_weight)
        self.seed = _check_int("seed", seed, 0)
        self.order = np.random.default_rng(self.seed).permutation(n)
        m = min(period, n - 1)
        # Floor splits of the path: consecutive cut points differ by >= 1 because
        # (N - 1) / m >= 1, so every segment has >= 2 learners.
        cuts = [i * (n - 1) // m for i in range(m + 1)] if m else []
        self.segments = [self.order[a : b + 1].tolist() for a, b in pairwise(cuts)]
        cycle = [self._segment_matrix(seg) for seg in self.segments]
        cycle += [torch.eye(n, dtype=torch.float64)] * (period - m)
        super().__init__(cycle, period=period)

    def _segment_matrix(self, segment: list[int]) -> torch.Tensor:
        """``s·I + (1 - s)·P`` with ``P`` the directed cycle ``seg[j]`` ← ``seg[j - 1]``."""
        senders = np.arange(self.n_learners)
        senders[segment] = np.roll(segment, 1)
        return _permutation_mixing([senders], self.self_weight)


class MatrixSchedule(_CyclicSchedule):
    """User-given periodic schedule ``W(k) = matrices[k % len(matrices)]``.

    Nothing is validated beyond conversion to 2-D float64 tensors, so arbitrary
    (possibly invalid) graphs can be fed to ``check_inner_schedule`` /
    ``check_outer_schedule``.

    Args:
        matrices: non-empty sequence of ``[N, N]`` array-likes; ``N`` is taken from the first.
        period: the ``B`` claimed for Assumption 1; defaults to ``len(matrices)``.
    """

    def __init__(self, matrices: Sequence, *, period: int | None = None) -> None:
        if len(matrices) == 0:
            raise ValueError("matrices must be a non-empty sequence of [N, N] matrices.")
        cycle = [torch.as_tensor(np.asarray(m, dtype=np.float64)) for m in matrices]
        for i, m in enumerate(cycle):
            if m.ndim != 2:
                raise ValueError(f"matrices[{i}] must be 2-D [N, N], got shape {tuple(m.shape)}.")
        self.n_learners = int(cycle[0].shape[0])
        period = len(cycle) if period is None else _check_int("period", period, 1)
        super().__init__(cycle, period=period)


# ---------------------------------------------------------------------------
# assumption checks
# ---------------------------------------------------------------------------


def _reachable(adj: np.ndarray, start: int = 0) -> np.ndarray:
    """Boolean ``[N]`` mask of nodes reachable from ``start`` along ``adj[i, j]`` (i → j)."""
    seen = np.zeros(adj.shape[0], dtype=bool)
    seen[start] = True
    frontier = [start]
    while frontier:
        nxt = np.flatnonzero(adj[frontier].any(axis=0) & ~seen)
        seen[nxt] = True
        frontier = nxt.tolist()
    return seen


def _check_matrix(w, n: int, step: str) -> np.ndarray:
    """Shape / finiteness of one matrix; returns it as ``[N, N]`` float64 numpy."""
    w = np.asarray(w.detach().cpu() if isinstance(w, torch.Tensor) else w, dtype=np.float64)
    if w.shape != (n, n):
        raise ValueError(
            f"Mixing matrix at {step} has shape {w.shape}, expected [{n}, {n}] "
            f"(square, N = n_learners = {n}). Fix the schedule's matrices or its n_learners."
        )
    if not np.isfinite(w).all():
        raise ValueError(
            f"Mixing matrix at {step} has non-finite entries at (v, v') "
            f"{_fmt_entries(np.argwhere(~np.isfinite(w)))}; all weights must be finite."
        )
    return w


def _check_steps(schedule, horizon, epsilon, atol, *, outer: bool) -> tuple[float, list]:
    """Per-step checks (shape, 2(i), Assumption 3 if ``outer``, 2(ii)); returns ε, supports."""
    n = _check_int("schedule.n_learners", schedule.n_learners, 1)
    horizon = _check_int("horizon", horizon, 1)
    if epsilon is not None and not (isinstance(epsilon, int | float) and 0.0 < epsilon <= 1.0):
        raise ValueError(f"epsilon must be in (0, 1] or None, got {epsilon!r}.")
    if not (isinstance(atol, int | float) and atol >= 0.0):
        raise ValueError(f"atol must be a float >= 0, got {atol!r}.")
    name, t = ("W̄(n)", "n") if outer else ("W(k)", "k")
    where = " (required of the outer matrix by Assumption 3)" if outer else ""
    supports, mats = [], []
    for k in range(horizon):
        step = f"{t}={k}"
        w = _check_matrix(schedule(k), n, step)
        if (w < 0).any():
            raise GraphAssumptionError(
                f"Assumption 2(i) (doubly stochastic) violated{where} by {name} at {step}: "
                f"negative entries (v, v') {_fmt_entries(np.argwhere(w < 0), w)}. Mixing "
                "weights must be nonnegative; use e.g. s·I + (1 - s)·P with P a permutation."
            )
        rows, cols = w.sum(axis=1), w.sum(axis=0)
        bad_r = np.flatnonzero(np.abs(rows - 1.0) > atol)
        bad_c = np.flatnonzero(np.abs(cols - 1.0) > atol)
        if bad_r.size or bad_c.size:
            sums = [
                f"{what} at {idx} {bad[:_MAX_LISTED].tolist()} (sums "
                f"{np.round(tot[bad[:_MAX_LISTED]], 6).tolist()})"
                for what, idx, bad, tot in (
                    ("row sums W·1 ≠ 1", "rows", bad_r, rows),
                    ("column sums 1ᵀW ≠ 1", "columns", bad_c, cols),
                )
                if bad.size
            ]
            raise GraphAssumptionError(
                f"Assumption 2(i) (doubly stochastic) violated{where} by {name} at {step}: "
                f"{'; '.join(sums)}, atol={atol:g}. Weights that are only row-stochastic bias "
                "the consensus towards some learners; use a doubly stochastic matrix, e.g. "
                "Metropolis weights 1/(1 + max(deg v, deg v')) on an undirected graph, or a "
                "convex combination of permutation matrices."
            )
        if outer and (w <= 0).any():
            raise GraphAssumptionError(
                f"Assumption 3 (outer graph complete) violated by {name} at {step}: entries "
                f"(v, v') {_fmt_entries(np.argwhere(w <= 0))} are 0, but every learner must "
                "receive from every other at every outer step. Use CompleteSchedule "
                "(W̄ = 1/N everywhere) for the outer loop."
            )
        supports.append(w > 0)
        mats.append(w)
    # ε: the smallest positive weight seen (positive self-weights included); a zero
    # self-weight is then the only way to break 2(ii), and is reported as such.
    eps = float(min(w[w > 0].min() for w in mats)) if epsilon is None else float(epsilon)
    label = f"Assumption 2(ii) (non-degenerate, ε = {eps:.6g}" + (
        ", the smallest positive weight seen)" if epsilon is None else ")"
    )
    for k, w in enumerate(mats):
        diag = np.flatnonzero(w.diagonal() < max(eps - atol, np.finfo(np.float64).tiny))
        if diag.size:
            raise GraphAssumptionError(
                f"{label} violated{where} by {name} at {t}={k}: self-weights W[v, v] = "
                f"{np.round(w.diagonal()[diag[:_MAX_LISTED]], 6).tolist()} of learners "
                f"{diag[:_MAX_LISTED].tolist()} are below ε. Every learner must keep its own "
                "estimate with weight ≥ ε ((v, v) ∈ E(k)); e.g. use (I + W)/2, which stays "
                "doubly stochastic" + (", or lower epsilon." if epsilon is not None else ".")
            )
        small = np.argwhere((w > 0) & (w < eps - atol))
        if small.size:
            raise GraphAssumptionError(
                f"{label} violated{where} by {name} at {t}={k}: positive weights (v, v') "
                f"{_fmt_entries(small, w)} are below ε. Raise those link weights or lower epsilon."
            )
    return eps, supports


def check_inner_schedule(
    schedule: MixingSchedule,
    *,
    horizon: int = 100,
    epsilon: float | None = None,
    atol: float = 1e-12,
) -> float:
    """Check Assumptions 1 and 2 for the inner-loop schedule over ``k < horizon``.

    Args:
        schedule: the ``W(k)`` schedule, with ``n_learners`` and ``period`` (= ``B``).
        horizon: steps checked; Assumption 1 is checked for every window
            ``[k, k + B - 1]`` with ``k < horizon``.
        epsilon: required non-degeneracy constant; ``None`` uses the smallest positive
            weight (diagonal included) seen, after requiring every diagonal entry ``> 0``.
        atol: tolerance of the row/column sums and of the ``≥ ε`` comparisons.

    Returns:
        The non-degeneracy constant ``ε`` of Assumption 2(ii).

    Raises:
        GraphAssumptionError: an assumption fails; the message names it, the step and
            the offending entries, and suggests a fix.
        ValueError: wrong shape, non-finite entries or invalid arguments.
    """
    b = _check_int("schedule.period", schedule.period, 1)
    horizon = _check_int("horizon", horizon, 1)
    # Windows starting before `horizon` reach step horizon + B - 2.
    eps, supports = _check_steps(schedule, horizon + b - 1, epsilon, atol, outer=False)
    # Sliding count of how many steps in the window contain each edge: O((horizon + B)·N²).
    count = np.sum(supports[:b], axis=0, dtype=np.int64)
    for k in range(horizon):
        if k:
            count += supports[k + b - 1]
            count -= supports[k - 1]
        union = count > 0
        fwd, bwd = _reachable(union.T), _reachable(union)  # 0 → others, others → 0
        if not (fwd.all() and bwd.all()):
            parts = []
            if not fwd.all():
                parts.append(f"learners {np.flatnonzero(~fwd).tolist()} never hear from learner 0")
            if not bwd.all():
                parts.append(f"learners {np.flatnonzero(~bwd).tolist()} never reach learner 0")
            union_name = f"E({k})" if b == 1 else f"E({k}) ∪ … ∪ E({k + b - 1})"
            raise GraphAssumptionError(
                f"Assumption 1 (B-strong connectivity, B = period = {b}) violated for the window "
                f"k={k}..{k + b - 1}: the union graph {union_name} is not strongly connected "
                f"({'; '.join(parts)}). Fix: add links (e.g. a ring) so that every "
                "window of `period` steps connects all learners, or increase the schedule's "
                "period if the union over a longer window is connected."
            )
    return eps


def check_outer_schedule(
    schedule: MixingSchedule,
    *,
    horizon: int = 100,
    epsilon: float | None = None,
    atol: float = 1e-12,
) -> float:
    """Check Assumption 3 for the outer-loop schedule ``W̄(n)`` over ``n < horizon``.

    ``W̄(n)`` must be complete (all entries ``> 0``) at every step, doubly stochastic and
    non-degenerate; completeness makes every single step strongly connected, so
    Assumption 1 holds with ``B = 1``.

    Args:
        schedule: the ``W̄(n)`` schedule.
        horizon: steps checked.
        epsilon: required ``ε̄``; ``None`` uses the smallest weight seen.
        atol: tolerance of the row/column sums and of the ``≥ ε`` comparisons.

    Returns:
        The non-degeneracy constant ``ε̄``.

    Raises:
        GraphAssumptionError: an assumption fails (message as in ``check_inner_schedule``).
        ValueError: wrong shape, non-finite entries or invalid arguments.
    """
    eps, _ = _check_steps(schedule, horizon, epsilon, atol, outer=True)
    return eps



# ---------------------------------------------------------------------------
# links that fail
# ---------------------------------------------------------------------------


def strongly_connected(support: np.ndarray) -> bool:
    """Whether the graph of ``support`` ``[N, N]`` (``support[v, v']``: v hears v') is
    strongly connected."""
    support = np.asarray(support, dtype=bool)
    return bool(_reachable(support.T).all() and _reachable(support).all())


class LinkFailures:
    """Inner rounds over links that fail: each link of ``W(k)`` is down with probability
    ``p`` in each round, independently, drawn from ``(seed, round)`` so that every learner
    computes the same realised graph without exchanging anything.

    A link is a channel between two learners: when it fails neither hears the other. The
    failed weights move to the diagonals (each learner keeps its own value instead), and a
    directed ``W`` is then balanced back to doubly stochastic by Sinkhorn scaling on the
    support that remains (the diagonal is positive, so the scaling exists). The realised
    matrix is checked against Assumption 2 before use; Assumption 1 cannot be promised
    for random failures and is checked, per inner process, on the union of its rounds
    (:meth:`DICRL.inner_process <dicrl_torch.algos.dicrl.DICRL.inner_process>` reports the
    processes whose union was not strongly connected).

    Args:
        p: the probability that a link fails in a round, in [0, 1).
        seed: the run's seed.
    """

    def __init__(self, p: float, seed: int) -> None:
        from dicrl_torch.checks import setting_number

        self.p = setting_number("link_failure", p, low=0, high=1, high_open=True,
                                example=0.2, why="the probability that a link fails in a "
                                                  "round")
        self.seed = _check_int("link_seed", seed, 0)

    def realise(self, W: torch.Tensor, *round_id: int) -> torch.Tensor:
        """``W`` ``[N, N]`` with this round's failed links removed and re-weighted.

        Args:
            round_id: non-negative ints naming the round (e.g. outer iteration, inner
                process, inner step); the same ids give the same failures everywhere.
        """
        if self.p == 0.0:
            return W
        w = W.detach().to(torch.float64).numpy().copy()
        n = w.shape[0]
        draws = np.random.default_rng([self.seed, *round_id]).random(n * (n - 1) // 2)
        pairs = [(u, v) for u in range(n) for v in range(u + 1, n)]
        for (u, v), draw in zip(pairs, draws, strict=True):
            if draw < self.p and (w[u, v] > 0 or w[v, u] > 0):
                w[u, u] += w[u, v]
                w[v, v] += w[v, u]
                w[u, v] = w[v, u] = 0.0
        if np.abs(w.sum(0) - 1.0).max() > 1e-15:  # a directed W: balance the columns
            # A doubly stochastic matrix is a mix of permutations, so its links lie on
            # cycles: a link between two strongly connected components of what is left
            # (a directed cycle with one link down) cannot carry weight. Drop those, then
            # scale on the rest (every link on a cycle, the diagonal positive: it converges).
            reach = np.stack([_reachable(w.T > 0, v) for v in range(n)])  # [v, u]: v -> u
            across = (w > 0) & ~(reach & reach.T)
            w[np.diag_indices(n)] += np.where(across, w, 0.0).sum(1)
            w[across] = 0.0
            for _ in range(10_000):
                w /= w.sum(0, keepdims=True)
                w /= w.sum(1, keepdims=True)
                if np.abs(w.sum(0) - 1.0).max() <= 1e-14:
                    break
        realised = torch.from_numpy(w)
        _check_steps(MatrixSchedule([w]), 1, None, 1e-12, outer=False)  # Assumption 2
        return realised
