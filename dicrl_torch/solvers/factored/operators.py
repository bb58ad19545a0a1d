"""The per-expert operators both passes are built from (package docstring).

The joint transition is a product of per-expert "move or stay" operators; each
function here applies one of them along one state axis of an actions-first tensor
``[a_1, .., a_k, s_1, .., s_N]``, in expectation or in log space (trajectory backup).
"""

from __future__ import annotations

import math

import torch


def exp_ftz(x: torch.Tensor) -> torch.Tensor:
    """``exp(x)`` that never produces denormal floats.

    Denormals make x86 arithmetic several times slower, and occupancies of unlikely
    states reach them constantly.
    Arguments below a floor are raised to it, so such a term reads ``exp(floor)``
    (1.8e-35 in float32, 1e-304 in float64) instead of something smaller: far below
    the dtype's resolution of any sum it enters, and far enough above the denormal
    range that products with transition probabilities stay normal. ``clamp_min`` reads
    ``x`` once, which keeps inductor's loop fused (a ``where`` on ``x`` made it
    materialise all S·A).
    """
    log_tiny = -80.0 if x.dtype == torch.float32 else -700.0
    return torch.exp(x.clamp_min(log_tiny))


def logsumexp(q: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """Stable logsumexp over ``dims``; a slice that is all ``-inf`` gives ``-inf``."""
    top = q.amax(dims, keepdim=True)
    finite = torch.isfinite(top)
    out = torch.log(exp_ftz(q - torch.where(finite, top, 0.0)).sum(dims)) + top.squeeze(dims)
    return torch.where(finite.squeeze(dims), out, top.squeeze(dims))


def mix(moved: torch.Tensor, stay: torch.Tensor, p: float, log_space: bool) -> torch.Tensor:
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


def apply_expert(X: torch.Tensor, i: int, n_experts: int, nxt_t: torch.Tensor, p: float,
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
    out = mix(moved, X.unsqueeze(0), p, log_space)
    if r_t is not None:
        rs = [A1] + [1] * (X.dim())
        rs[1 + axis] = S1
        out = out + r_t.reshape(rs)
    return out


def prepare(V_next: torch.Tensor, r_t: torch.Tensor, nxt_t: torch.Tensor, p: float,
            gamma: float, trajectory: bool = False) -> torch.Tensor:
    """``γ V_{t+1}`` through the operators of experts N..2 (with their rewards):
    ``[A1]*(N-1) + [S1]*N``. Argument ``r_t`` is ``[N, A1, S1]``.

    With ``trajectory``: ``V_{t+1}`` through the log-space operators, with rewards
    ``r_i / γ`` (the ``γ`` is applied after expert 1's operator, in :func:`q_first`)."""
    N = V_next.dim()
    if trajectory:
        X = V_next
        for i in range(N - 1, 0, -1):
            X = apply_expert(X, i, N, nxt_t, p, r_t[i] / gamma, log_space=True)
        return X
    X = gamma * V_next
    for i in range(N - 1, 0, -1):
        X = apply_expert(X, i, N, nxt_t, p, r_t[i])
    return X


def mix_first(X: torch.Tensor, move_to: torch.Tensor, stay_at, p: float,
              log_space: bool = False) -> torch.Tensor:
    """Expert 1's operator at a set of its cells: ``[A1, C] + [A1]*(N-1) + [S1]*(N-1)``
    (arguments as in :func:`q_first`)."""
    k = (X.dim() - 1) // 2  # N-1 action axes come first; expert 1's state axis is k
    Xm = X.movedim(k, 0)  # [S1, A.., S..] (a view)
    stay = Xm[stay_at]
    if isinstance(stay_at, slice):
        stay = stay.unsqueeze(0)
    return mix(Xm[move_to], stay, p, log_space)


def q_first(X: torch.Tensor, r1_t: torch.Tensor, move_to: torch.Tensor, stay_at, p: float,
            gamma: float | None = None) -> torch.Tensor:
    """Q (without the joint term) for every expert-1 action at a set of expert-1 cells.

    Args:
        X: ``prepare(..)`` output, ``[A1]*(N-1) + [S1]*N``.
        r1_t: ``[A1, C]`` expert 1's reward at those cells.
        move_to: ``[A1, C]`` where each action's success leads.
        stay_at: the cells themselves: a ``slice`` (structured, cheap) or ``[A1, C]``.
        p: success probability.
        gamma: None for the causal backup (``X`` already holds ``γ V``); the discount
            for the trajectory backup (``X`` is mixed in log space, then scaled by it).

    Returns:
        ``[A1, C] + [A1]*(N-1) + [S1]*(N-1)``.
    """
    q = mix_first(X, move_to, stay_at, p, log_space=gamma is not None)
    if gamma is not None:
        q = gamma * q
    return q + r1_t.reshape(tuple(r1_t.shape) + (1,) * (X.dim() - 1))
