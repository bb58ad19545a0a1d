"""The forward (occupancy) pass of the factored solver (package docstring).

The state occupancy ``d_t`` ``[S1]*N`` is pushed through the transposed operators,
written as pulls over each expert's predecessor table; per-expert state-action
marginals fall out of the partial contractions.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from dicrl_torch.solvers.factored.operators import (
    apply_expert,
    exp_ftz,
    mix_first,
    prepare,
    q_first,
)

if TYPE_CHECKING:
    from dicrl_torch.solvers.factored.solver import FactoredSoftBellman

# A tilt factor of the trajectory forward pass is at most 1/min(p, 1-p); exponents
# above this bound only occur on zero-weight (padding / impossible) terms, which are
# clamped so that 0 · exp(.) stays 0 instead of 0 · inf = NaN.
TILT_EXP_MAX = 60.0


def forward_kernel(V_next, shift, r_t, nxt_t, p, gamma, cells: slice, w_self, move_src,
                   move_nxt, move_r, w_move, trajectory: bool = False):
    """Expert 1's transposed operator applied to ``ρ_t = d_t π_t`` (other experts'
    actions kept), as a pull: each target cell in ``cells`` gathers its self term
    (structured) and its move predecessors (one table lookup each). With
    ``trajectory``, expert 1's operator is the tilted one (package docstring).

    Args:
        V_next: ``[S1]*N`` values ``V_{t+1}``.
        shift: ``[S1]*N`` = ``log d_t - (V_t - g)``, ``-inf`` where ``d_t = 0`` (one
            merged tensor: keeping ``log d`` apart would cost a second gather per term).
        cells: the target cells (a slice of expert 1's cells).
        w_self: ``[A1, C]`` P(s|s, a). move_src / move_nxt / move_r / w_move:
            ``[K, A1, C]`` the k-th move predecessor of each target, where its action
            leads, its expert-1 reward and its probability (0 for padding).

    Returns:
        ``Z`` ``[C] + [A1]*(N-1) + [S1]*(N-1)``.
    """
    if trajectory:
        return forward_kernel_trajectory(V_next, shift, r_t, nxt_t, p, gamma, cells, w_self,
                                         move_src, move_nxt, move_r, w_move)
    X = prepare(V_next, r_t, nxt_t, p, gamma)
    pad = (1,) * (V_next.dim() - 1)

    def bcast(x):  # [., C, S2..] -> [., C, 1 (other actions).., S2..]
        return x.reshape(tuple(x.shape[:2]) + pad + tuple(x.shape[2:]))

    def rho_sum(q, sh, w):  # Σ_a1 w · exp(Q + log d - V)
        return (w.reshape(tuple(w.shape) + pad + pad) * exp_ftz(q + bcast(sh))).sum(0)

    q_self = q_first(X, r_t[0][:, cells], nxt_t[:, cells], cells, p)
    Z = rho_sum(q_self, shift[cells].unsqueeze(0), w_self)
    for k in range(move_src.shape[0]):
        q_mv = q_first(X, move_r[k], move_nxt[k], move_src[k], p)
        Z = Z + rho_sum(q_mv, shift[move_src[k]], w_move[k])
    return Z


def forward_kernel_trajectory(V_next, shift, r_t, nxt_t, p, gamma, cells: slice, w_self,
                              move_src, move_nxt, move_r, w_move):
    """:func:`forward_kernel` for the trajectory backup: ``ρ_t`` through expert 1's
    tilted operator ``P_1(s1'|s1, a1) exp(Λ_1(s1', ..) − L_t(s, a))``.

    With ``X = Λ_1 + Σ_{i≥2} r_i/γ`` (the log-space :func:`prepare`) and ``Y`` its mix
    at a predecessor (``L_t + Σ_{i≥2} r_i/γ``), the rewards cancel in ``X − Y`` and
    ``log ρ_t = γY + r_1 + shift``; one exponent per term, bounded above by
    ``log(1/w)``, so neither factor is formed alone (either may overflow).
    """
    X = prepare(V_next, r_t, nxt_t, p, gamma, trajectory=True)
    pad = (1,) * (V_next.dim() - 1)
    k = (X.dim() - 1) // 2
    target = X.movedim(k, 0)[cells].unsqueeze(0)  # Λ_1 at the target cells [1, C, A.., S..]

    def bcast(x):  # [., C, S2..] -> [., C, 1 (other actions).., S2..]
        return x.reshape(tuple(x.shape[:2]) + pad + tuple(x.shape[2:]))

    def rho_sum(y, r1, sh, w):  # Σ_a1 w · exp(log ρ − Y + Λ_1(target))
        r1 = r1.reshape(tuple(r1.shape) + pad + pad)
        e = ((gamma - 1.0) * y + r1 + bcast(sh) + target).clamp_max(TILT_EXP_MAX)
        # y = -inf: no successor is allowed, so ρ = 0 there (and -inf - -inf is NaN).
        e = torch.where(y > -math.inf, e, -math.inf)
        return (w.reshape(tuple(w.shape) + pad + pad) * exp_ftz(e)).sum(0)

    y_self = mix_first(X, nxt_t[:, cells], cells, p, log_space=True)
    Z = rho_sum(y_self, r_t[0][:, cells], shift[cells].unsqueeze(0), w_self)
    for j in range(move_src.shape[0]):
        y_mv = mix_first(X, move_nxt[j], move_src[j], p, log_space=True)
        Z = Z + rho_sum(y_mv, move_r[j], shift[move_src[j]], w_move[j])
    return Z


def pull_tilted_kernel(Y: torch.Tensor, M: torch.Tensor, Xt: torch.Tensor,
                       w_self: torch.Tensor, a_index: torch.Tensor, move_src: torch.Tensor,
                       w_move: torch.Tensor) -> torch.Tensor:
    """:func:`pull_kernel` through one expert's *tilted* operator (trajectory backup):
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
        e = (Xt.unsqueeze(0) - m).clamp_max(TILT_EXP_MAX)
        e = torch.where(m > -math.inf, e, -math.inf)  # no mass where M = -inf
        return (w.reshape(tuple(w.shape) + pad) * y * exp_ftz(e)).sum(0)

    out = term(w_self, Y, M)
    for k in range(move_src.shape[0]):
        out = out + term(w_move[k], Y[a_index, move_src[k]], M[a_index, move_src[k]])
    return out


def pull_kernel(Y: torch.Tensor, w_self: torch.Tensor, a_index: torch.Tensor,
                move_src: torch.Tensor, w_move: torch.Tensor) -> torch.Tensor:
    """One expert's transposed operator summed over its action (experts 2..N, whose
    state-action distribution is already an array): ``Y`` ``[A1, S1, ...]`` ->
    ``[S1', ...]``. Tables as in :func:`forward_kernel`, over all cells."""
    pad = (1,) * (Y.dim() - 2)
    out = (w_self.reshape(tuple(w_self.shape) + pad) * Y).sum(0)
    for k in range(move_src.shape[0]):
        out = out + (w_move[k].reshape(tuple(w_move[k].shape) + pad)
                     * Y[a_index, move_src[k]]).sum(0)
    return out


def forward_pass(solver: FactoredSoftBellman, V: torch.Tensor, centres: torch.Tensor,
                 r_t: torch.Tensor, g: torch.Tensor | None, L1: torch.Tensor,
                 trajectory: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Discounted occupancies of the policy of a backward pass (:func:`.backward_pass`),
    in the solver's units (rewards divided by ``τ``).

    Args:
        V: ``[T+1] + [S1]*N`` values relative to the per-step baseline; centres: ``[T+1]``
            the step's centres ``m_t`` (``Q_t - V_t`` reads ``q(v_{t+1}) - v_t - m_t``).
        r_t: ``[N, A1, S1]`` per-expert rewards; g: ``[S1]*N`` joint term, or None.
        L1: ``[T, A1] + [S1]*N`` expert 1's partial logsumexp from the backward pass.
        trajectory: push through the tilted dynamics of the trajectory backup.

    Returns:
        ``(state, local)`` float64: ``[S1]*N`` ``Σ_t γ^t d_t`` and ``[N, S1, A1]`` each
        expert's marginal ``Σ_t γ^t ρ_t^i``.
    """
    m = solver.model
    N, T, gamma = m.n_experts, m.horizon, m.gamma
    centres = centres.to(solver.dtype)
    d = m.initial_distribution().to(solver.device, solver.dtype)
    occ_state = torch.zeros(m.state_shape, dtype=torch.float64, device=solver.device)
    occ_local = torch.zeros(N, m.n_actions, m.n_cells, dtype=torch.float64,
                            device=solver.device)
    rest = tuple(range(2, N + 1))  # the other experts' state axes of [A1, S1, S..]
    steps = range(T)
    if solver.progress:
        from tqdm.auto import tqdm
        steps = tqdm(steps, desc="forward", leave=False)
    for t in steps:
        disc = gamma**t
        occ_state += disc * d
        # The step's logsumexp over actions, at the scale of the values it backed up.
        Vlse = V[t] + centres[t]
        if g is not None:
            Vlse = Vlse - g
        # log d - V; -inf where d = 0 or V = -inf (hard masks: d is 0 there too).
        ok = (d > 0) & torch.isfinite(Vlse)
        shift = torch.where(ok, torch.log(d) - Vlse, -math.inf).contiguous()
        # Expert 1's marginal from its partial logsumexp: Σ_s' d(s) π^1(a1|s).
        rho1 = exp_ftz(L1[t] + shift.unsqueeze(0))
        # (sum(dim=()) would reduce every axis, hence the guard for one expert)
        occ_local[0] += disc * (rho1.sum(rest) if rest else rho1).double()
        Z = forward_step(solver, V[t + 1], shift, r_t, trajectory).movedim(0, N - 1)
        chain = log_chain(solver, V[t + 1], r_t) if trajectory else None
        for i in range(1, N):  # Z: [A_i, .., A_N, S1, .., SN]
            k = Z.dim() - N
            # float32 partial sums, float64 accumulation over time
            occ_local[i] += disc * Z.sum(
                dim=tuple(a for a in range(Z.dim()) if a not in (0, k + i))).double()
            if trajectory:  # expert i's tilted operator, from Λ_{i+1} (chain[i])
                Xn = chain[i]  # [A_{i+1}.., S..]
                M = apply_expert(Xn, i, N, solver.nxt_t, solver.p, None, log_space=True)
                Z = pull_tilted(solver, Z.movedim(k + i, 1), M.movedim(k + i, 1),
                                Xn.movedim(k - 1 + i, 0)).movedim(0, k + i - 1)
            else:
                Z = pull(solver, Z.movedim(k + i, 1)).movedim(0, k + i - 1)
        d = Z.contiguous()  # a permuted view otherwise: odd strides recompile kernels
    return occ_state, occ_local.transpose(1, 2).contiguous()


def log_chain(solver: FactoredSoftBellman, V_next: torch.Tensor, r_t: torch.Tensor
              ) -> dict[int, torch.Tensor]:
    """The partial log-expectations of :func:`prepare` (trajectory backup), keyed by
    the 0-based expert whose pull uses them: ``{N-1: V_{t+1}, i: experts N-1..i+1
    applied}`` for ``i = 1..N-1``; entry ``i`` has shape ``[A1]*(N-1-i) + [S1]*N``."""
    N = V_next.dim()
    chain = {N - 1: V_next}
    X = V_next
    for i in range(N - 1, 1, -1):
        X = apply_expert(X, i, N, solver.nxt_t, solver.p, r_t[i] / solver.model.gamma,
                         log_space=True)
        chain[i - 1] = X
    return chain


def pull_tilted(solver: FactoredSoftBellman, Y: torch.Tensor, M: torch.Tensor,
                Xt: torch.Tensor) -> torch.Tensor:
    """``[A1, S1, ...]`` -> ``[S1', ...]``: see :func:`pull_tilted_kernel`."""
    f = solver._pull_tilted_compiled if solver.use_compile else pull_tilted_kernel
    return f(Y.contiguous(), M.contiguous(), Xt.contiguous(), solver.w_self, solver.a_index,
             solver.move_src, solver.w_move)


def pull(solver: FactoredSoftBellman, Y: torch.Tensor) -> torch.Tensor:
    """``[A1, S1, ...]`` -> ``[S1', ...]``: see :func:`pull_kernel`."""
    f = solver._pull_compiled if solver.use_compile else pull_kernel
    return f(Y.contiguous(), solver.w_self, solver.a_index, solver.move_src, solver.w_move)


def forward_step(solver: FactoredSoftBellman, V_next, shift, r_t, trajectory: bool = False):
    """``Z`` ``[S1'] + [A1]*(N-1) + [S1]*(N-1)``: ρ_t through expert 1's operator
    (tilted with ``trajectory``)."""
    S1 = solver.model.n_cells
    move_r = r_t[0][solver.a_index.unsqueeze(0), solver.move_src]  # [K, A1, S1]
    args = (solver.nxt_t, solver.p, solver.model.gamma)
    if solver.use_compile:
        return solver._fwd(V_next.clone(), shift, r_t, *args, slice(None), solver.w_self,
                           solver.move_src, solver.move_nxt, move_r, solver.w_move, trajectory)
    # Eager: chunk over the *target* cells of expert 1 (the self term needs no
    # gather, so its cells are a slice of the full tables).
    parts = []
    for c0 in range(0, S1, solver.chunk_cells):
        c = slice(c0, min(S1, c0 + solver.chunk_cells))
        parts.append(forward_kernel(
            V_next, shift, r_t, *args, c, solver.w_self[:, c], solver.move_src[:, :, c],
            solver.move_nxt[:, :, c], move_r[:, :, c], solver.w_move[:, :, c], trajectory))
    return torch.cat(parts, 0)
