"""Exact finite-horizon soft-Bellman solver on the factored grid-world model (docs/design.md §4).

Backward pass, for t = T-1 .. 0 (``V_T = 0``)::

    Q_t(s, a) = Σ_i r_i(s_i, a_i) + g(s) + γ E[V_{t+1}(s') | s, a]
    V_t(s)    = logsumexp_a Q_t(s, a),        π_t(a|s) = exp(Q_t(s, a) - V_t(s))

The joint transition is a product of per-expert "move or stay" operators, so
``E[V(s')]`` is computed by applying expert ``i``'s operator along axis ``i`` of ``V``.
Because an operator's probabilities sum to one, a reward term that does not depend on
``s_i`` passes through it unchanged; hence we apply the operators of experts N..2,
adding ``r_i`` after each (arrays of ``S·A^(N-1)`` entries), and fuse the last operator
with the logsumexp over all actions. Only that last fused stage touches all
``S·A`` pairs; it is chunked over expert 1's cell (eager) or compiled into one
vectorised loop nest by ``torch.compile`` so the ``S·A`` array is never materialised.

Tensor layout: *actions first*, ``[a_1, .., a_k, s_1, .., s_N]``, so every reduction
and gather runs over contiguous state memory.

Forward pass: the state occupancy is pushed through the transposed operators. A push
is a scatter; we write it as a *pull* over a small predecessor table of each expert
(``pred[a, s', k]``: the cells that reach ``s'`` under ``a``, with their probabilities),
which compiles to plain gathers. Per-expert state-action marginals fall out of the
partial contractions; feature expectations are contracted from them, never from a
per-step ``S·A`` array.

Hard constraints are ``-inf`` rewards; a temperature ``τ`` is a reward scaling
(``V = τ logsumexp(Q/τ)``) and ``τ = 0`` gives the hard-max DP.

**Two backups.** ``solve(..., backup="causal")`` (default) is the maximum-*causal*-entropy
model above. ``backup="trajectory"`` is the (trajectory-level) maximum-entropy model of
Ziebart et al. (2008), ``P(ζ) ∝ P0(s_0) Π_t P(s_{t+1}|s_t, a_t) exp(Σ_t r(s_t, a_t))``,
whose backward recursion replaces the expected next value by its log-expected-exp::

    L_t(s, a) = log E[exp V_{t+1}(s') | s, a],    Q_t = r + γ L_t,    V_t = logsumexp_a Q_t

computed through the same per-expert operators in log space: each operator combines
its two outcomes (move, stay) with a ``logaddexp``, i.e. each element subtracts its own
max, so nothing overflows or underflows to a wrong value in float32. Rewards pass
through (``log E[exp(X + c)] = c + log E[exp X]`` for ``c`` constant along the mixed
axis), divided by ``γ`` so that the final ``γ ·`` gives them back unscaled.

*Discounting.* ``γ`` multiplies the continuation ``L_t`` exactly where it multiplies
``E[V_{t+1}]`` in the causal backup. At ``γ = 1`` this is Ziebart's model exactly; for
any ``γ`` and deterministic dynamics, ``L_t = V_{t+1}(s')`` and both backups coincide.
For ``γ < 1`` it is the exact solution of the variational problem
``max E_{π, P̃}[Σ_t γ^t (r_t + H(π_t(·|s_t))) − Σ_t γ^{t+1} KL(P̃_t(·|s_t, a_t) ‖ P)]``:
the model also picks the *dynamics* ``P̃`` (this is how the trajectory-level model
differs from the causal one), paying for departing from ``P`` at the discount of the
state it arrives in. Its optimum is ``π_t = exp(Q_t − V_t)`` and the optimistic,
tilted dynamics ``P̃_t(s'|s, a) = P(s'|s, a) exp(V_{t+1}(s') − L_t(s, a))``, with
``P̃_0(s) ∝ P0(s) exp V_0(s)``. (Putting ``γ`` inside, ``log E[exp γV]``, would charge
the KL at ``γ^t``; the exact Gibbs law of the discounted return needs a time-varying
temperature ``γ^{-t}`` and would not coincide with the causal backup for deterministic
dynamics.) The γ-discounted log-likelihood of a trajectory then telescopes to
``Σ_t γ^t r(s_t, a_t) + γ^T V_T(s_T) − log Σ_s P0(s) exp V_0(s)`` (+ terms of ``P``
and ``P0`` that do not depend on the model); see ``dicrl_torch.algos.greedy``.

The trajectory forward pass pushes ``ρ_t = d_t π_t`` through the tilted dynamics. The
tilt ``exp(V_{t+1}(s') − L_t(s, a))`` is split over the experts along the chain of
partial log-expectations ``Λ`` the backward pass builds (``Λ_N = V_{t+1}``, ``Λ_{i-1} =
log E_i[exp Λ_i]``, ``Λ_0 = L_t``): expert ``i``'s factor ``P_i exp(Λ_i − Λ_{i-1})`` is a
proper transition kernel whose weights are at most ``1/min(p, 1-p)``, so each push stays
mass-preserving and bounded, and the per-expert marginals are read off exactly as in
the causal pass.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import torch

from dicrl_torch.envs.grid import TabularGridModel
from dicrl_torch.features.base import EnvKind
from dicrl_torch.features.bases import FactoredReward

# Below this many state-action pairs the eager path is fast enough and compiling
# (seconds, once per shape) does not pay off.
COMPILE_MIN_PAIRS = 5_000_000
# Above this |V|, float32 values resolve policies worse than ~1e-3 per step: warn.
FLOAT32_VALUE_LIMIT = 1e4


# ----------------------------------------------------------------------------- kernels
def _exp_ftz(x: torch.Tensor) -> torch.Tensor:
    """``exp(x)`` that never produces denormal floats.

    Denormals make x86 arithmetic several times slower, and occupancies of unlikely
    states reach them constantly (measured: 0.8 s -> 1.7 s per 3-expert forward step).
    Arguments below a floor are raised to it, so such a term reads ``exp(floor)``
    (1.8e-35 in float32, 1e-304 in float64) instead of something smaller: far below
    the dtype's resolution of any sum it enters, and far enough above the denormal
    range that products with transition probabilities stay normal. ``clamp_min`` reads
    ``x`` once, which keeps inductor's loop fused (a ``where`` on ``x`` made it
    materialise all S·A).
    """
    log_tiny = -80.0 if x.dtype == torch.float32 else -700.0
    return torch.exp(x.clamp_min(log_tiny))


def _logsumexp(q: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """Stable logsumexp over ``dims``; a slice that is all ``-inf`` gives ``-inf``."""
    top = q.amax(dims, keepdim=True)
    finite = torch.isfinite(top)
    out = torch.log(_exp_ftz(q - torch.where(finite, top, 0.0)).sum(dims)) + top.squeeze(dims)
    return torch.where(finite.squeeze(dims), out, top.squeeze(dims))


# A tilt factor of the trajectory forward pass is at most 1/min(p, 1-p); exponents
# above this bound only occur on zero-weight (padding / impossible) terms, which are
# clamped so that 0 · exp(.) stays 0 instead of 0 · inf = NaN.
_TILT_EXP_MAX = 60.0


def _mix(moved: torch.Tensor, stay: torch.Tensor, p: float, log_space: bool) -> torch.Tensor:
    """Combine a move outcome and a stay outcome of one expert.

    ``p · moved + (1 - p) · stay`` (an expectation), or in log space
    ``log(p e^moved + (1 - p) e^stay)`` by a ``logaddexp`` (stable: per-element max).
    With ``p = 1`` only ``moved`` counts: ``(1 - p) · (-inf)`` would be NaN.
    """
    if p == 1.0:
        return moved + 0.0 if log_space else p * moved
    if log_space:
        return torch.logaddexp(moved + math.log(p), stay + math.log1p(-p))
    return p * moved + (1.0 - p) * stay


def _apply_expert(X: torch.Tensor, i: int, n_experts: int, nxt_t: torch.Tensor, p: float,
                  r_t: torch.Tensor | None, log_space: bool = False) -> torch.Tensor:
    """Apply expert ``i``'s move-or-stay operator along its state axis.

    Args:
        X: ``[A1]*k + [S1]*N`` (``k`` action axes already made).
        i: expert index (its state axis is ``k + i``).
        n_experts: ``N``.
        nxt_t: ``[A1, S1]`` successful-move targets (transposed table).
        p: success probability.
        r_t: ``[A1, S1]`` reward of expert ``i`` added after the operator, or None.
        log_space: ``log E[exp X]`` instead of ``E[X]`` (trajectory backup).

    Returns:
        ``[A1] + [A1]*k + [S1]*N``: the new action axis ``a_i`` comes first.
    """
    k = X.dim() - n_experts
    axis = k + i
    A1, S1 = nxt_t.shape
    moved = X.index_select(axis, nxt_t.reshape(-1))  # [.., A1*S1 (a-major), ..]
    shape = list(X.shape)
    shape[axis:axis + 1] = [A1, S1]
    moved = moved.reshape(shape).movedim(axis, 0)
    out = _mix(moved, X.unsqueeze(0), p, log_space)
    if r_t is not None:
        rs = [A1] + [1] * (X.dim())
        rs[1 + axis] = S1
        out = out + r_t.reshape(rs)
    return out


def _prepare(V_next: torch.Tensor, r_t: torch.Tensor, nxt_t: torch.Tensor, p: float,
             gamma: float, trajectory: bool = False) -> torch.Tensor:
    """``γ V_{t+1}`` through the operators of experts N..2 (with their rewards):
    ``[A1]*(N-1) + [S1]*N``. Argument ``r_t`` is ``[N, A1, S1]``.

    With ``trajectory``: ``V_{t+1}`` through the log-space operators, with rewards
    ``r_i / γ`` (the ``γ`` is applied after expert 1's operator, in :func:`_q_first`)."""
    N = V_next.dim()
    if trajectory:
        X = V_next
        for i in range(N - 1, 0, -1):
            X = _apply_expert(X, i, N, nxt_t, p, r_t[i] / gamma, log_space=True)
        return X
    X = gamma * V_next
    for i in range(N - 1, 0, -1):
        X = _apply_expert(X, i, N, nxt_t, p, r_t[i])
    return X


def _mix_first(X: torch.Tensor, move_to: torch.Tensor, stay_at, p: float,
               log_space: bool = False) -> torch.Tensor:
    """Expert 1's operator at a set of its cells: ``[A1, C] + [A1]*(N-1) + [S1]*(N-1)``
    (arguments as in :func:`_q_first`)."""
    k = (X.dim() - 1) // 2  # N-1 action axes come first; expert 1's state axis is k
    Xm = X.movedim(k, 0)  # [S1, A.., S..] (a view)
    stay = Xm[stay_at]
    if isinstance(stay_at, slice):
        stay = stay.unsqueeze(0)
    return _mix(Xm[move_to], stay, p, log_space)


def _q_first(X: torch.Tensor, r1_t: torch.Tensor, move_to: torch.Tensor, stay_at, p: float,
             gamma: float | None = None) -> torch.Tensor:
    """Q (without the joint term) for every expert-1 action at a set of expert-1 cells.

    Args:
        X: ``_prepare(..)`` output, ``[A1]*(N-1) + [S1]*N``.
        r1_t: ``[A1, C]`` expert 1's reward at those cells.
        move_to: ``[A1, C]`` where each action's success leads.
        stay_at: the cells themselves: a ``slice`` (structured, cheap) or ``[A1, C]``.
        p: success probability.
        gamma: None for the causal backup (``X`` already holds ``γ V``); the discount
            for the trajectory backup (``X`` is mixed in log space, then scaled by it).

    Returns:
        ``[A1, C] + [A1]*(N-1) + [S1]*(N-1)``.
    """
    q = _mix_first(X, move_to, stay_at, p, log_space=gamma is not None)
    if gamma is not None:
        q = gamma * q
    return q + r1_t.reshape(tuple(r1_t.shape) + (1,) * (X.dim() - 1))


def _backward_kernel(V_next, r_t, nxt_t, p, gamma, cells: slice, hard: bool,
                     trajectory: bool = False):
    """Backward step for the expert-1 cells ``cells`` (``trajectory``: ME backup).

    Returns:
        ``(L1, V)``: ``L1`` ``[A1, C] + [S1]*(N-1)`` logsumexp (or max) over the other
        experts' actions for each expert-1 action, and ``V`` ``[C] + [S1]*(N-1)`` the
        reduction of ``L1`` over expert 1's action (no joint term).
    """
    X = _prepare(V_next, r_t, nxt_t, p, gamma, trajectory)
    q = _q_first(X, r_t[0][:, cells], nxt_t[:, cells], cells, p,
                 gamma if trajectory else None)  # [A1, C, A.., S..]
    N = V_next.dim()
    others = tuple(range(2, N + 1))
    if hard:
        L1 = q.amax(others) if others else q
        return L1, L1.amax(0)
    L1 = _logsumexp(q, others) if others else q
    return L1, _logsumexp(L1, (0,))


def _forward_kernel(V_next, shift, r_t, nxt_t, p, gamma, cells: slice, w_self, move_src,
                    move_nxt, move_r, w_move, trajectory: bool = False):
    """Expert 1's transposed operator applied to ``ρ_t = d_t π_t`` (other experts'
    actions kept), as a pull: each target cell in ``cells`` gathers its self term
    (structured) and its move predecessors (one table lookup each). With
    ``trajectory``, expert 1's operator is the tilted one (module docstring).

    Args:
        V_next: ``[S1]*N``. shift: ``[S1]*N`` = ``log d_t - (V_t - g)``, ``-inf`` where
            ``d_t = 0``. (One merged tensor: keeping ``log d`` apart costs a second
            gather, +25% time, for accuracy that float32 ``V`` limits anyway.)
        cells: the target cells (a slice of expert 1's cells).
        w_self: ``[A1, C]`` P(s|s, a). move_src / move_nxt / move_r / w_move:
            ``[K, A1, C]`` the k-th move predecessor of each target, where its action
            leads, its expert-1 reward and its probability (0 for padding).

    Returns:
        ``Z`` ``[C] + [A1]*(N-1) + [S1]*(N-1)``.
    """
    if trajectory:
        return _forward_kernel_trajectory(V_next, shift, r_t, nxt_t, p, gamma, cells, w_self,
                                          move_src, move_nxt, move_r, w_move)
    X = _prepare(V_next, r_t, nxt_t, p, gamma)
    pad = (1,) * (V_next.dim() - 1)

    def bcast(x):  # [., C, S2..] -> [., C, 1 (other actions).., S2..]
        return x.reshape(tuple(x.shape[:2]) + pad + tuple(x.shape[2:]))

    def rho_sum(q, sh, w):  # Σ_a1 w · exp(Q + log d - V)
        return (w.reshape(tuple(w.shape) + pad + pad) * _exp_ftz(q + bcast(sh))).sum(0)

    q_self = _q_first(X, r_t[0][:, cells], nxt_t[:, cells], cells, p)
    Z = rho_sum(q_self, shift[cells].unsqueeze(0), w_self)
    for k in range(move_src.shape[0]):
        q_mv = _q_first(X, move_r[k], move_nxt[k], move_src[k], p)
        Z = Z + rho_sum(q_mv, shift[move_src[k]], w_move[k])
    return Z


def _forward_kernel_trajectory(V_next, shift, r_t, nxt_t, p, gamma, cells: slice, w_self,
                               move_src, move_nxt, move_r, w_move):
    """:func:`_forward_kernel` for the trajectory backup: ``ρ_t`` through expert 1's
    tilted operator ``P_1(s1'|s1, a1) exp(Λ_1(s1', ..) − L_t(s, a))``.

    With ``X = Λ_1 + Σ_{i≥2} r_i/γ`` (the log-space :func:`_prepare`) and ``Y`` its mix
    at a predecessor (``L_t + Σ_{i≥2} r_i/γ``), the rewards cancel in ``X − Y`` and
    ``log ρ_t = γY + r_1 + shift``; one exponent per term, bounded above by
    ``log(1/w)``, so neither factor is formed alone (either may overflow).
    """
    X = _prepare(V_next, r_t, nxt_t, p, gamma, trajectory=True)
    pad = (1,) * (V_next.dim() - 1)
    k = (X.dim() - 1) // 2
    target = X.movedim(k, 0)[cells].unsqueeze(0)  # Λ_1 at the target cells [1, C, A.., S..]

    def bcast(x):  # [., C, S2..] -> [., C, 1 (other actions).., S2..]
        return x.reshape(tuple(x.shape[:2]) + pad + tuple(x.shape[2:]))

    def rho_sum(y, r1, sh, w):  # Σ_a1 w · exp(log ρ − Y + Λ_1(target))
        r1 = r1.reshape(tuple(r1.shape) + pad + pad)
        e = ((gamma - 1.0) * y + r1 + bcast(sh) + target).clamp_max(_TILT_EXP_MAX)
        # y = -inf: no successor is allowed, so ρ = 0 there (and -inf - -inf is NaN).
        e = torch.where(y > -math.inf, e, -math.inf)
        return (w.reshape(tuple(w.shape) + pad + pad) * _exp_ftz(e)).sum(0)

    y_self = _mix_first(X, nxt_t[:, cells], cells, p, log_space=True)
    Z = rho_sum(y_self, r_t[0][:, cells], shift[cells].unsqueeze(0), w_self)
    for j in range(move_src.shape[0]):
        y_mv = _mix_first(X, move_nxt[j], move_src[j], p, log_space=True)
        Z = Z + rho_sum(y_mv, move_r[j], shift[move_src[j]], w_move[j])
    return Z


def _pull_tilted_kernel(Y: torch.Tensor, M: torch.Tensor, Xt: torch.Tensor,
                        w_self: torch.Tensor, a_index: torch.Tensor, move_src: torch.Tensor,
                        w_move: torch.Tensor) -> torch.Tensor:
    """:func:`_pull_kernel` through one expert's *tilted* operator (trajectory backup):
    ``out[s'] = Σ_a Σ_s w(s→s'|a) Y[a, s] exp(Xt[s'] − M[a, s])``.

    Args:
        Y: ``[A1, S1, ...]`` mass.
        M: ``[A1, S1, ...]`` ``log E[exp Xt]`` under each (action, cell) (``Λ_{i-1}``).
        Xt: ``[S1', ...]`` the next-level log values ``Λ_i``.

    Returns:
        ``[S1', ...]``.
    """
    pad = (1,) * (Y.dim() - 2)

    def term(w, y, m):
        e = (Xt.unsqueeze(0) - m).clamp_max(_TILT_EXP_MAX)
        e = torch.where(m > -math.inf, e, -math.inf)  # no mass where M = -inf
        return (w.reshape(tuple(w.shape) + pad) * y * _exp_ftz(e)).sum(0)

    out = term(w_self, Y, M)
    for k in range(move_src.shape[0]):
        out = out + term(w_move[k], Y[a_index, move_src[k]], M[a_index, move_src[k]])
    return out


def _pull_kernel(Y: torch.Tensor, w_self: torch.Tensor, a_index: torch.Tensor,
                 move_src: torch.Tensor, w_move: torch.Tensor) -> torch.Tensor:
    """One expert's transposed operator summed over its action (experts 2..N, whose
    state-action distribution is already an array): ``Y`` ``[A1, S1, ...]`` ->
    ``[S1', ...]``. Tables as in :func:`_forward_kernel`, over all cells."""
    pad = (1,) * (Y.dim() - 2)
    out = (w_self.reshape(tuple(w_self.shape) + pad) * Y).sum(0)
    for k in range(move_src.shape[0]):
        out = out + (w_move[k].reshape(tuple(w_move[k].shape) + pad)
                     * Y[a_index, move_src[k]]).sum(0)
    return out


# ---------------------------------------------------------------------------- solution
@dataclass
class SoftBellmanSolution:
    """Result of :meth:`FactoredSoftBellman.solve`.

    Attributes:
        V: ``[T+1, S1, .., S1]`` values (``V[T] = 0``), in the solver dtype.
        state_occupancy: ``[S1]*N`` float64, ``Σ_t γ^t d_t(s)`` (None if not computed).
        local_occupancy: ``[N, S1, A1]`` float64, ``Σ_t γ^t ρ_t^i(s_i, a_i)`` — each
            expert's marginal of the discounted state-action occupancy.
        backup: ``"causal"`` (MCE) or ``"trajectory"`` (ME, Ziebart 2008): the model
            the values, policy and occupancies belong to.
        log_partition: causal: ``Σ_s P0(s) V_0(s)``; trajectory:
            ``τ log Σ_s P0(s) exp(V_0(s)/τ)`` (``log Z``).
    """

    V: torch.Tensor
    reward: FactoredReward
    temperature: float
    solver: FactoredSoftBellman = field(repr=False)
    state_occupancy: torch.Tensor | None = None
    local_occupancy: torch.Tensor | None = None
    timings: dict[str, float] = field(default_factory=dict)
    backup: str = "causal"

    @property
    def log_partition(self) -> float:
        p0 = self.solver.model.initial_distribution().to(self.V.device)
        if self.backup == "trajectory":
            tau = self.temperature
            v0 = self.V[0].double().reshape(-1) / tau
            return tau * float(torch.logsumexp(torch.log(p0.reshape(-1)) + v0, 0))
        # (states outside P0's support may have V = -inf: 0 · -inf would be NaN)
        return float((p0 * torch.where(p0 > 0, self.V[0].double(), 0.0)).sum())

    def feature_expectation(self, features) -> torch.Tensor:
        """``[l]`` discounted feature expectation ``E[Σ_t γ^t φ(S_t, A_t)]``."""
        if self.local_occupancy is None:
            raise ValueError("Run solve(..., forward=True) to get occupancies.")
        return features.expectation(self.local_occupancy.cpu(), self.state_occupancy.cpu())

    def q_values_at(self, t: int, cells: torch.Tensor) -> torch.Tensor:
        """``Q_t`` at a batch of joint states: cells ``[B, N]`` -> ``[B, A1**N]``
        (joint action index with expert 1 most significant)."""
        return self.solver.q_values_at(self, t, cells)

    def policy_at(self, t: int, cells: torch.Tensor, tie_tol: float = 1e-6) -> torch.Tensor:
        """``π_t(·|s)`` ``[B, A1**N]`` at joint states ``cells`` ``[B, N]``. With
        temperature 0 the policy is uniform over the maximising joint actions.

        At a state where every action is forbidden (``Q_t = -inf`` throughout: the model
        holds it unreachable) the policy is uniform, not NaN: a trajectory-backup (ME)
        policy plans with optimistic dynamics and can reach such states under the real
        ones, e.g. in ``dicrl_torch.metrics.rollout_true_cmg``."""
        q = self.q_values_at(t, cells).double()
        dead = ~torch.isfinite(q).any(1, keepdim=True)  # [B, 1]
        if dead.any():
            q = torch.where(dead, 0.0, q)
        if self.temperature == 0.0:
            best = q.amax(1, keepdim=True)
            tie = (q >= best - tie_tol * best.abs().clamp_min(1.0)) & torch.isfinite(q)
            return tie.double() / tie.sum(1, keepdim=True)
        return torch.softmax(q / self.temperature, 1)

    def policy_dense(self, t: int) -> torch.Tensor:
        """``[S, A]`` policy at step ``t`` (tiny instances only)."""
        m = self.solver.model
        if m.n_pairs > 5_000_000:
            raise ValueError(f"policy_dense on {m.n_pairs:,} pairs; use policy_at on a batch.")
        cells = torch.cartesian_prod(*[torch.arange(m.n_cells)] * m.n_experts).reshape(
            -1, m.n_experts)
        return self.policy_at(t, cells)


# ------------------------------------------------------------------------------ solver
class FactoredSoftBellman:
    """Exact soft-Bellman solver on a :class:`TabularGridModel`.

    Args:
        model: the learner's tabular model.
        device: ``"cpu"``, ``"cuda"`` or a ``torch.device``.
        dtype: value dtype, ``torch.float32`` (fast default) or ``torch.float64``
            (checks, extreme weights); the names ``"float32"``/``"float64"`` work too.
        compile: ``True``/``False``/``"auto"`` — fuse the ``S·A`` stages with
            ``torch.compile``; ``"auto"`` compiles above 5M pairs.
        chunk_cells: expert-1 cells per chunk on the eager path (bounds memory).
        progress: show a tqdm bar over time steps.
    """

    # The kind of environment the solver serves: "grid", the tabular grid world (as its
    # bases, features.base.Basis). experiments/config_checks.py refuses it elsewhere.
    env_kind: EnvKind = "grid"

    def __init__(self, *, model: TabularGridModel, device: str | torch.device = "cpu",
                 dtype: torch.dtype | str = torch.float32, compile: bool | str = "auto",
                 chunk_cells: int = 9, progress: bool = False) -> None:
        if isinstance(dtype, str):
            dtype = {"float32": torch.float32, "float64": torch.float64}.get(dtype, dtype)
        if compile not in (True, False, "auto"):
            raise ValueError(f"compile must be True, False or 'auto', got {compile!r}.")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}.")
        self.model = model
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device='cuda' requested but CUDA is not available; use 'cpu'.")
        self.dtype = dtype
        self.chunk_cells = max(1, int(chunk_cells))
        self.progress = progress
        self.use_compile = (model.n_pairs >= COMPILE_MIN_PAIRS) if compile == "auto" else compile
        S1, A1 = model.n_cells, model.n_actions
        dev = self.device
        self.nxt_t = model.next_cell.t().contiguous().to(dev)  # [A1, S1]
        self.p = model.p_success
        self.a_index = torch.arange(A1, device=dev).unsqueeze(1).expand(A1, S1).contiguous()
        self.w_self, self.move_src, self.w_move = self._predecessors()
        self.move_nxt = self.nxt_t[self.a_index.unsqueeze(0), self.move_src]  # [K, A1, S1]
        self._bwd = self._fwd = None
        self._warned_value = 0.0  # the |V| of the last float32 precision warning
        if self.use_compile:
            self._bwd = torch.compile(_backward_kernel, dynamic=False)
            self._fwd = torch.compile(_forward_kernel, dynamic=False)
            self._pull_compiled = torch.compile(_pull_kernel, dynamic=False)
            self._pull_tilted_compiled = torch.compile(_pull_tilted_kernel, dynamic=False)

    def _predecessors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The transposed operator of one expert, for pulls.

        Returns:
            ``w_self`` ``[A1, S1]`` = P(s|s, a); ``move_src`` ``[K, A1, S1]`` the other
            cells that reach each target under each action (padded with the target
            itself) and ``w_move`` ``[K, A1, S1]`` their probabilities (0 for padding).
        """
        P1 = self.model.expert_transition()  # [S1, A1, S1']
        S1, A1 = self.model.n_cells, self.model.n_actions
        eye = torch.arange(S1)
        w_self = P1[eye, :, eye].t()  # [A1, S1]
        off = P1.clone()
        off[eye, :, eye] = 0.0
        K = max(1, int((off > 0).sum(0).max()))
        src = eye.expand(K, A1, S1).clone()
        w = torch.zeros(K, A1, S1, dtype=torch.float64)
        for a in range(A1):
            for t in range(S1):
                srcs = torch.nonzero(off[:, a, t]).flatten()
                src[:len(srcs), a, t] = srcs
                w[:len(srcs), a, t] = off[srcs, a, t]
        dev, dt = self.device, self.dtype
        return w_self.to(dev, dt).contiguous(), src.to(dev), w.to(dev, dt)

    # ---------------------------------------------------------------- reward handling
    def _tables(self, reward: FactoredReward, temperature: float):
        m = self.model
        scale = 1.0 if temperature == 0.0 else 1.0 / temperature
        local = reward.local
        if tuple(local.shape) != (m.n_experts, m.n_cells, m.n_actions):
            raise ValueError(f"reward.local must be [{m.n_experts}, {m.n_cells}, "
                             f"{m.n_actions}], got {tuple(local.shape)}.")
        joint = reward.joint
        if torch.isnan(local).any() or (joint is not None and torch.isnan(joint).any()):
            raise ValueError("The reward contains NaN; check the weights (ω_r, λ, ω_c).")
        r_t = (local * scale).transpose(1, 2).to(self.device, self.dtype).contiguous()
        g = None
        if reward.joint is not None:
            g = (reward.joint * scale).reshape(m.state_shape).to(self.device, self.dtype)
        return r_t, g

    # ------------------------------------------------------------------------ backward
    def _backward_step(self, V_next, r_t, hard: bool, trajectory: bool = False
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L1 [A1] + [S1]*N, Vlse [S1]*N)`` for one step (see _backward_kernel)."""
        S1 = self.model.n_cells
        gamma = self.model.gamma
        if self.use_compile:
            # A fresh tensor, not a view into V: views at other offsets would recompile.
            return self._bwd(V_next.clone(), r_t, self.nxt_t, self.p, gamma, slice(None), hard,
                             trajectory)
        L1 = torch.empty((self.model.n_actions,) + tuple(V_next.shape), dtype=V_next.dtype,
                         device=V_next.device)
        V = torch.empty_like(V_next)
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            L1[:, c], V[c] = _backward_kernel(V_next, r_t, self.nxt_t, self.p, gamma, c, hard,
                                              trajectory)
        return L1, V

    def solve(self, reward: FactoredReward, *, temperature: float = 1.0,
              forward: bool = True, terminal_value: torch.Tensor | None = None,
              backup: str = "causal") -> SoftBellmanSolution:
        """Backward (and optionally forward) pass for ``reward``.

        Args:
            reward: per-expert tables and joint-state term; ``-inf`` marks forbidden
                pairs (hard constraints).
            temperature: ``τ > 0`` soft-optimal; ``0`` hard-max DP (no forward pass).
            forward: also compute occupancies (needs ``τ > 0``).
            terminal_value: ``V_T`` ``[S1]*N`` (default 0). Nothing is scored at the
                last state ``s_T``, so hard constraints on states must also be put
                here (``-inf``), or the last move may enter a forbidden state.
            backup: ``"causal"`` — maximum causal entropy, ``Q = r + γ E[V']``;
                ``"trajectory"`` — maximum (trajectory) entropy, ``Q = r + γ τ log
                E[exp(V'/τ)]``, with occupancies of its tilted dynamics (module
                docstring). Needs ``temperature > 0``.
        """
        if backup not in ("causal", "trajectory"):
            raise ValueError(f"backup must be 'causal' (MCE) or 'trajectory' (ME), got "
                             f"{backup!r}.")
        if backup == "trajectory" and temperature == 0.0:
            raise ValueError("backup='trajectory' needs a soft model: use temperature > 0 "
                             "(its τ -> 0 limit is an optimistic max over outcomes).")
        if not (temperature >= 0.0 and math.isfinite(temperature)):
            raise ValueError(f"temperature must be a finite number >= 0, got {temperature!r}.")
        if forward and temperature == 0.0:
            raise ValueError("The forward pass needs a soft policy: use temperature > 0 "
                             "(or forward=False for the hard-max DP).")
        m = self.model
        hard = temperature == 0.0
        r_t, g = self._tables(reward, temperature)
        T = m.horizon
        sync = torch.cuda.synchronize if self.device.type == "cuda" else (lambda: None)
        t0 = time.perf_counter()
        V = torch.zeros((T + 1,) + m.state_shape, dtype=self.dtype, device=self.device)
        if terminal_value is not None:
            if tuple(terminal_value.shape) != m.state_shape:
                raise ValueError(f"terminal_value must have shape {m.state_shape}, got "
                                 f"{tuple(terminal_value.shape)}.")
            if torch.isnan(terminal_value).any():
                raise ValueError("terminal_value contains NaN.")
            scale = 1.0 if temperature == 0.0 else 1.0 / temperature
            V[T] = terminal_value.to(self.device, self.dtype) * scale
        # Expert 1's partial logsumexp, kept for the forward pass's expert-1 marginal.
        L1 = (torch.empty((T, m.n_actions) + m.state_shape, dtype=self.dtype,
                          device=self.device) if forward else None)
        steps = range(T - 1, -1, -1)
        if self.progress:
            from tqdm.auto import tqdm
            steps = tqdm(steps, desc="backward", leave=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for t in steps:
                l1, v = self._backward_step(V[t + 1], r_t, hard, backup == "trajectory")
                V[t] = v if g is None else v + g
                if L1 is not None:
                    L1[t] = l1
        if not hard and temperature != 1.0:
            V *= temperature
        sync()
        t1 = time.perf_counter()
        if self.dtype == torch.float32:
            # One pass without a copy (a masked select of V took 0.7 s per 3-expert
            # solve); states with no allowed action hold -inf and are masked out only then.
            lo, hi = torch.aminmax(V)
            if lo == -math.inf:
                lo, hi = torch.aminmax(V.masked_fill(V == -math.inf, 0.0))
            v_max = max(abs(float(lo)), abs(float(hi)))
            # Again only when |V| has doubled since: a training run solves hundreds of
            # times at about the same scale, and one line says it.
            if v_max > max(FLOAT32_VALUE_LIMIT, 2.0 * self._warned_value):
                # float32 resolves V to ~|V| * 6e-8; beyond this, policies (exp(Q - V))
                # lose per-step accuracy of order 1e-3 or worse and occupancies drift.
                self._warned_value = v_max
                warnings.warn(
                    f"|V| reaches {v_max:.3g}: float32 cannot resolve the policy accurately "
                    f"at this scale; use dtype=torch.float64 (or smaller weights). Repeated "
                    f"only if |V| doubles.", RuntimeWarning, stacklevel=2)
        sol = SoftBellmanSolution(V=V, reward=reward, temperature=float(temperature), solver=self,
                                  backup=backup)
        sol.timings["backward_s"] = t1 - t0
        if forward:
            self._forward(sol, r_t, g, L1)
            sync()
            sol.timings["forward_s"] = time.perf_counter() - t1
        return sol

    # ------------------------------------------------------------------------- forward
    def _forward(self, sol: SoftBellmanSolution, r_t, g, L1: torch.Tensor) -> None:
        m = self.model
        N, T, gamma = m.n_experts, m.horizon, m.gamma
        tau = sol.temperature
        V = sol.V if tau == 1.0 else sol.V / tau
        d = m.initial_distribution().to(self.device, self.dtype)
        occ_state = torch.zeros(m.state_shape, dtype=torch.float64, device=self.device)
        occ_local = torch.zeros(N, m.n_actions, m.n_cells, dtype=torch.float64,
                                device=self.device)
        rest = tuple(range(2, N + 1))  # the other experts' state axes of [A1, S1, S..]
        trajectory = sol.backup == "trajectory"
        steps = range(T)
        if self.progress:
            from tqdm.auto import tqdm
            steps = tqdm(steps, desc="forward", leave=False)
        for t in steps:
            disc = gamma**t
            occ_state += disc * d
            Vlse = V[t] if g is None else V[t] - g
            # log d - V; -inf where d = 0 or V = -inf (hard masks: d is 0 there too).
            ok = (d > 0) & torch.isfinite(Vlse)
            shift = torch.where(ok, torch.log(d) - Vlse, -math.inf).contiguous()
            # Expert 1's marginal from its partial logsumexp: Σ_s' d(s) π^1(a1|s).
            rho1 = _exp_ftz(L1[t] + shift.unsqueeze(0))
            # (sum(dim=()) would reduce every axis, hence the guard for one expert)
            occ_local[0] += disc * (rho1.sum(rest) if rest else rho1).double()
            Z = self._forward_step(V[t + 1], shift, r_t, trajectory).movedim(0, N - 1)
            chain = self._log_chain(V[t + 1], r_t) if trajectory else None
            for i in range(1, N):  # Z: [A_i, .., A_N, S1, .., SN]
                k = Z.dim() - N
                # float32 partial sums, float64 accumulation over time
                occ_local[i] += disc * Z.sum(
                    dim=tuple(a for a in range(Z.dim()) if a not in (0, k + i))).double()
                if trajectory:  # expert i's tilted operator, from Λ_{i+1} (chain[i])
                    Xn = chain[i]  # [A_{i+1}.., S..]
                    M = _apply_expert(Xn, i, N, self.nxt_t, self.p, None, log_space=True)
                    Z = self._pull_tilted(Z.movedim(k + i, 1), M.movedim(k + i, 1),
                                          Xn.movedim(k - 1 + i, 0)).movedim(0, k + i - 1)
                else:
                    Z = self._pull(Z.movedim(k + i, 1)).movedim(0, k + i - 1)
            d = Z.contiguous()  # a permuted view otherwise: odd strides recompile kernels
        sol.state_occupancy = occ_state
        sol.local_occupancy = occ_local.transpose(1, 2).contiguous()  # [N, S1, A1]

    def _log_chain(self, V_next: torch.Tensor, r_t: torch.Tensor) -> dict[int, torch.Tensor]:
        """The partial log-expectations of :func:`_prepare` (trajectory backup), keyed by
        the 0-based expert whose pull uses them: ``{N-1: V_{t+1}, i: experts N-1..i+1
        applied}`` for ``i = 1..N-1``; entry ``i`` has shape ``[A1]*(N-1-i) + [S1]*N``."""
        N = V_next.dim()
        chain = {N - 1: V_next}
        X = V_next
        for i in range(N - 1, 1, -1):
            X = _apply_expert(X, i, N, self.nxt_t, self.p, r_t[i] / self.model.gamma,
                              log_space=True)
            chain[i - 1] = X
        return chain

    def _pull_tilted(self, Y: torch.Tensor, M: torch.Tensor, Xt: torch.Tensor) -> torch.Tensor:
        """``[A1, S1, ...]`` -> ``[S1', ...]``: see :func:`_pull_tilted_kernel`."""
        f = self._pull_tilted_compiled if self.use_compile else _pull_tilted_kernel
        return f(Y.contiguous(), M.contiguous(), Xt.contiguous(), self.w_self, self.a_index,
                 self.move_src, self.w_move)

    def _pull(self, Y: torch.Tensor) -> torch.Tensor:
        """``[A1, S1, ...]`` -> ``[S1', ...]``: see :func:`_pull_kernel`."""
        f = self._pull_compiled if self.use_compile else _pull_kernel
        return f(Y.contiguous(), self.w_self, self.a_index, self.move_src, self.w_move)

    def _forward_step(self, V_next, shift, r_t, trajectory: bool = False):
        """``Z`` ``[S1'] + [A1]*(N-1) + [S1]*(N-1)``: ρ_t through expert 1's operator
        (tilted with ``trajectory``)."""
        S1 = self.model.n_cells
        move_r = r_t[0][self.a_index.unsqueeze(0), self.move_src]  # [K, A1, S1]
        args = (self.nxt_t, self.p, self.model.gamma)
        if self.use_compile:
            return self._fwd(V_next.clone(), shift, r_t, *args, slice(None), self.w_self,
                             self.move_src, self.move_nxt, move_r, self.w_move, trajectory)
        # Eager: chunk over the *target* cells of expert 1 (the self term needs no
        # gather, so its cells are a slice of the full tables).
        parts = []
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            parts.append(_forward_kernel(
                V_next, shift, r_t, *args, c, self.w_self[:, c], self.move_src[:, :, c],
                self.move_nxt[:, :, c], move_r[:, :, c], self.w_move[:, :, c], trajectory))
        return torch.cat(parts, 0)

    # ------------------------------------------------------------------ point queries
    def q_values_at(self, sol: SoftBellmanSolution, t: int, cells: torch.Tensor) -> torch.Tensor:
        """``[B, A1**N]`` Q-values at joint states ``cells`` ``[B, N]`` (in the
        solution's reward units)."""
        m = self.model
        N, A1 = m.n_experts, m.n_actions
        if not 0 <= t < m.horizon:
            raise ValueError(f"t must lie in [0, {m.horizon}), got {t}.")
        cells = torch.as_tensor(cells, dtype=torch.int64, device=self.device)
        tau = sol.temperature
        r_t, g = self._tables(sol.reward, tau)
        Vn = sol.V[t + 1] if tau in (0.0, 1.0) else sol.V[t + 1] / tau
        B = cells.shape[0]
        # Candidate next cells per expert: [stay, move(a) for a in A1] -> [B, N, 1+A1].
        cand = torch.cat([cells.unsqueeze(-1), self.nxt_t.t()[cells]], -1)
        idx = [cand[:, i].reshape([B] + [1] * i + [A1 + 1] + [1] * (N - 1 - i))
               for i in range(N)]
        U = Vn[tuple(idx)].double()  # [B, (1+A1)^N]
        log_space = sol.backup == "trajectory"  # log E[exp V'] instead of E[V']
        for i in range(N):  # axis 1+i: [stay, moves] -> actions
            U = U.movedim(1 + i, 0)
            U = _mix(U[1:], U[:1], self.p, log_space)
            U = U.movedim(0, 1 + i)
        q = m.gamma * U
        for i in range(N):
            shape = [B] + [1] * N
            shape[1 + i] = A1
            q = q + r_t[i].t()[cells[:, i]].double().reshape(shape)
        q = q.reshape(B, -1)
        if g is not None:
            q = q + g[tuple(cells.t())].double().unsqueeze(1)
        return q if tau in (0.0, 1.0) else q * tau
