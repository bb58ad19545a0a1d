"""The backward (value) pass of the factored solver (package docstring).

For t = T-1 .. 0, ``V_t = logsumexp_a (r + g + γ E[V_{t+1}])`` (``max`` for the hard
DP, ``log E[exp V_{t+1}]`` for the trajectory backup), computed through the per-expert
operators of :mod:`.operators` so that only the last fused stage touches all ``S·A``
pairs.
"""

from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING

import torch

from dicrl_torch.solvers.factored.operators import logsumexp, prepare, q_first

if TYPE_CHECKING:
    from dicrl_torch.solvers.factored.solver import FactoredSoftBellman


def backward_kernel(V_next, r_t, nxt_t, p, gamma, cells: slice, hard: bool,
                    trajectory: bool = False):
    """Backward step for the expert-1 cells ``cells`` (``trajectory``: ME backup).

    Args:
        V_next: ``[S1]*N`` values ``V_{t+1}``.
        r_t: ``[N, A1, S1]`` per-expert rewards (transposed tables).
        nxt_t: ``[A1, S1]`` successful-move targets.
        cells: the expert-1 cells (a slice of ``S1``, ``C`` of them).

    Returns:
        ``(L1, V)``: ``L1`` ``[A1, C] + [S1]*(N-1)`` logsumexp (or max) over the other
        experts' actions for each expert-1 action, and ``V`` ``[C] + [S1]*(N-1)`` the
        reduction of ``L1`` over expert 1's action (no joint term).
    """
    X = prepare(V_next, r_t, nxt_t, p, gamma, trajectory)
    q = q_first(X, r_t[0][:, cells], nxt_t[:, cells], cells, p,
                gamma if trajectory else None)  # [A1, C, A.., S..]
    N = V_next.dim()
    others = tuple(range(2, N + 1))
    if hard:
        L1 = q.amax(others) if others else q
        return L1, L1.amax(0)
    L1 = logsumexp(q, others) if others else q
    return L1, logsumexp(L1, (0,))


def backward_step(solver: FactoredSoftBellman, V_next: torch.Tensor, r_t: torch.Tensor,
                  hard: bool, trajectory: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``(L1 [A1] + [S1]*N, Vlse [S1]*N)`` for one step (see :func:`backward_kernel`)."""
    model = solver.model
    S1, gamma = model.n_cells, model.gamma
    if solver.use_compile:
        # A fresh tensor, not a view into V: views at other offsets would recompile.
        return solver._bwd(V_next.clone(), r_t, solver.nxt_t, solver.p, gamma, slice(None),
                           hard, trajectory)
    L1 = torch.empty((model.n_actions,) + tuple(V_next.shape), dtype=V_next.dtype,
                     device=V_next.device)
    V = torch.empty_like(V_next)
    for c0 in range(0, S1, solver.chunk_cells):
        c = slice(c0, min(S1, c0 + solver.chunk_cells))
        L1[:, c], V[c] = backward_kernel(V_next, r_t, solver.nxt_t, solver.p, gamma, c, hard,
                                         trajectory)
    return L1, V


def midrange(v: torch.Tensor) -> torch.Tensor:
    """``(max + min) / 2`` over the finite entries of ``v`` (0-dim, ``v``'s dtype); 0 when
    none is finite (every state forbidden)."""
    finite = torch.isfinite(v)
    hi = torch.where(finite, v, -math.inf).amax()
    lo = torch.where(finite, v, math.inf).amin()
    mid = 0.5 * (hi + lo)
    return torch.where(torch.isfinite(mid), mid, 0.0)


def backward_pass(solver: FactoredSoftBellman, r_t: torch.Tensor, g: torch.Tensor | None,
                  terminal: torch.Tensor | None, *, hard: bool, trajectory: bool,
                  keep_l1: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """All ``T`` steps, in the solver's units (rewards already divided by ``τ``), with the
    values kept relative to a per-step baseline.

    ``V_t`` grows by about one step's reward per step back from the horizon: a constant
    over states that the policy ``exp(Q_t - V_t)`` does not depend on, but that float32
    would resolve only to ``|V_t| · 6e-8``. Each step therefore stores ``v_t = V'_t - m_t``,
    where ``V'_t`` is the step's backup of ``v_{t+1}`` (so ``V_t = V'_t + γ c_{t+1}``) and
    the scalar ``m_t`` centres it (midrange); the absolute values are ``V_t = v_t + c_t``
    with ``c_t = m_t + γ c_{t+1}``. The constant passes unchanged through every operator
    (an expectation or a log-expectation of a constant, a logsumexp over actions), so
    each step solves the same problem at the scale of the spread of ``V_t`` over states.

    Args:
        r_t: ``[N, A1, S1]`` per-expert rewards. g: ``[S1]*N`` joint term, or None.
        terminal: ``[S1]*N`` ``V_T`` (None: 0).
        keep_l1: keep expert 1's partial logsumexp for the forward pass.

    Returns:
        ``(v, m, L1)``: ``v`` ``[T+1] + [S1]*N`` the relative values; ``m`` ``[T+1]``
        float64 the per-step centres (``m_T`` that of ``V_T``); ``L1`` ``[T, A1] + [S1]*N``
        (relative to ``v_{t+1}``, as the forward pass reads it) or None.
    """
    m = solver.model
    T = m.horizon
    V = torch.zeros((T + 1,) + m.state_shape, dtype=solver.dtype, device=solver.device)
    centres = torch.zeros(T + 1, dtype=torch.float64, device=solver.device)
    if terminal is not None:
        centres[T] = mid = midrange(terminal)
        V[T] = terminal - mid
    # Expert 1's partial logsumexp, kept for the forward pass's expert-1 marginal.
    L1 = (torch.empty((T, m.n_actions) + m.state_shape, dtype=solver.dtype,
                      device=solver.device) if keep_l1 else None)
    steps = range(T - 1, -1, -1)
    if solver.progress:
        from tqdm.auto import tqdm
        steps = tqdm(steps, desc="backward", leave=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in steps:
            l1, v = backward_step(solver, V[t + 1], r_t, hard, trajectory)
            if g is not None:
                v = v + g
            centres[t] = mid = midrange(v)
            V[t] = v - mid
            if L1 is not None:
                L1[t] = l1
    return V, centres, L1
