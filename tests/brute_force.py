"""Independent brute-force references for tiny instances: an explicit joint transition
matrix enumerated from the grid geometry (not from the library's operators), dense
soft/hard Bellman recursions and dense occupancy propagation, in float64."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
import torch

MOVES = [(0, 0), (0, -1), (0, 1), (1, 0), (-1, 0), (1, -1), (-1, -1), (1, 1), (-1, 1)]


def joint_transition(size: int, n_experts: int, p: float) -> torch.Tensor:
    """Sparse ``[S*A, S]`` joint transition, enumerated outcome by outcome."""
    S1, A1 = size * size, len(MOVES)

    def outcomes(c: int, a: int) -> list[tuple[int, float]]:
        x, y = c % size, c // size
        dx, dy = MOVES[a]
        nx, ny = x + dx, y + dy
        target = ny * size + nx if 0 <= nx < size and 0 <= ny < size else c
        return [(target, p), (c, 1.0 - p)]

    per = [[outcomes(c, a) for a in range(A1)] for c in range(S1)]
    rows, cols, vals = [], [], []
    S = S1**n_experts
    for s_idx, cells in enumerate(itertools.product(range(S1), repeat=n_experts)):
        for a_idx, acts in enumerate(itertools.product(range(A1), repeat=n_experts)):
            row = s_idx * A1**n_experts + a_idx
            for combo in itertools.product(*[per[c][a] for c, a in zip(cells, acts, strict=True)]):
                target = 0
                prob = 1.0
                for cell, pr in combo:
                    target = target * S1 + cell
                    prob *= pr
                if prob > 0:
                    rows.append(row)
                    cols.append(target)
                    vals.append(prob)
    P = torch.sparse_coo_tensor(np.array([rows, cols]), np.array(vals),
                                (S * A1**n_experts, S)).coalesce()
    return P


def dense_solve(P: torch.Tensor, r: torch.Tensor, p0: torch.Tensor, T: int, gamma: float,
                temperature: float = 1.0, terminal: torch.Tensor | None = None):
    """Dense finite-horizon (soft) Bellman + occupancy.

    Returns V ``[T+1, S]``, policies ``[T, S, A]``, discounted occupancy ``[S, A]``,
    discounted state occupancy ``[S]``."""
    S, A = r.shape
    V = torch.zeros(T + 1, S, dtype=torch.float64)
    if terminal is not None:
        V[T] = terminal.reshape(S)
    pis = torch.zeros(T, S, A, dtype=torch.float64)
    for t in range(T - 1, -1, -1):
        # (sparse mm would turn 0 * -inf into nan: mask the -inf targets explicitly)
        vn = V[t + 1]
        EV = torch.sparse.mm(P, torch.where(torch.isfinite(vn), vn, 0.0).unsqueeze(1))
        reach_bad = torch.sparse.mm(P, (~torch.isfinite(vn)).double().unsqueeze(1)) > 0
        EV = torch.where(reach_bad, -torch.inf, EV).reshape(S, A)
        Q = r + gamma * EV
        if temperature == 0:
            V[t] = Q.max(1).values
            best = Q >= V[t].unsqueeze(1) - 1e-9 * V[t].abs().clamp_min(1).unsqueeze(1)
            pis[t] = best.double() / best.sum(1, keepdim=True)
        else:
            V[t] = temperature * torch.logsumexp(Q / temperature, 1)
            pis[t] = torch.softmax(Q / temperature, 1)
    occ, occ_s = discounted_occupancy(
        p0, pis, gamma, lambda t, rho: torch.sparse.mm(P.t(), rho.reshape(-1, 1)).reshape(S))
    return V, pis, occ, occ_s


def discounted_occupancy(d0: torch.Tensor, pis: torch.Tensor, gamma: float,
                         push: Callable[[int, torch.Tensor], torch.Tensor]
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Discounted occupancy ``[S, A]`` and state occupancy ``[S]`` of the policies
    ``pis`` ``[T, S, A]`` from the state distribution ``d0`` ``[S]``; ``push(t, rho)``
    takes the step-``t`` state-action distribution ``rho`` ``[S, A]`` to the next state
    distribution ``[S]``."""
    T, S, A = pis.shape
    d = d0
    occ = torch.zeros(S, A, dtype=torch.float64)
    occ_s = torch.zeros(S, dtype=torch.float64)
    for t in range(T):
        rho = d.unsqueeze(1) * pis[t]
        occ += gamma**t * rho
        occ_s += gamma**t * d
        d = push(t, rho)
    return occ, occ_s


def marginals(occ: torch.Tensor, n_experts: int, S1: int, A1: int) -> torch.Tensor:
    """``[N, S1, A1]`` per-expert marginals of a joint ``[S, A]`` occupancy."""
    full = occ.reshape((S1,) * n_experts + (A1,) * n_experts)
    out = []
    for i in range(n_experts):
        keep = (i, n_experts + i)
        dims = tuple(j for j in range(2 * n_experts) if j not in keep)
        out.append(full.sum(dims) if dims else full)
    return torch.stack(out)
