"""Exact finite-horizon soft-Bellman solver on the factored grid-world model (DESIGN §4).

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
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch

from dicrl_torch.envs.grid import TabularGridModel
from dicrl_torch.features.bases import FactoredReward

# Below this many state-action pairs the eager path is fast enough and compiling
# (seconds, once per shape) does not pay off.
COMPILE_MIN_PAIRS = 5_000_000


# ----------------------------------------------------------------------------- kernels
def _apply_expert(X: torch.Tensor, i: int, n_experts: int, nxt_t: torch.Tensor, p: float,
                  r_t: torch.Tensor | None) -> torch.Tensor:
    """Apply expert ``i``'s move-or-stay operator along its state axis.

    Args:
        X: ``[A1]*k + [S1]*N`` (``k`` action axes already made).
        i: expert index (its state axis is ``k + i``).
        n_experts: ``N``.
        nxt_t: ``[A1, S1]`` successful-move targets (transposed table).
        p: success probability.
        r_t: ``[A1, S1]`` reward of expert ``i`` added after the operator, or None.

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
    out = p * moved + (1.0 - p) * X.unsqueeze(0)
    if r_t is not None:
        rs = [A1] + [1] * (X.dim())
        rs[1 + axis] = S1
        out = out + r_t.reshape(rs)
    return out


def _prepare(V_next: torch.Tensor, r_t: torch.Tensor, nxt_t: torch.Tensor, p: float,
             gamma: float) -> torch.Tensor:
    """``γ V_{t+1}`` through the operators of experts N..2 (with their rewards):
    ``[A1]*(N-1) + [S1]*N``. Argument ``r_t`` is ``[N, A1, S1]``."""
    N = V_next.dim()
    X = gamma * V_next
    for i in range(N - 1, 0, -1):
        X = _apply_expert(X, i, N, nxt_t, p, r_t[i])
    return X


def _q_first(X: torch.Tensor, r1_t: torch.Tensor, nxt_t: torch.Tensor, p: float,
             s1: torch.Tensor, a1: torch.Tensor) -> torch.Tensor:
    """Q (without the joint term) at expert-1 cells ``s1`` and actions ``a1``, both
    ``[A1', C]`` index tensors, from ``X = _prepare(..)`` (``[A1]*(N-1) + [S1]*N``):
    returns ``[A1', C] + [A1]*(N-1) + [S1]*(N-1)``."""
    k = (X.dim() - 1) // 2  # N-1 action axes come first; expert 1's state axis is k
    n1 = nxt_t[a1, s1]  # [A1', C]
    Xm = X.movedim(k, 0)  # [S1, A.., S..]
    q = p * Xm[n1] + (1.0 - p) * Xm[s1]
    extra = [1] * (X.dim() - 1)
    return q + r1_t[a1, s1].reshape(list(s1.shape) + extra)


def _backward_kernel(V_next, r_t, nxt_t, p, gamma, s1, a1, hard: bool):
    """``Vlse_t[s1, ...] = lse (or max) over all actions of Q`` (no joint term), for the
    expert-1 cells in the ``[A1, C]`` index ``s1``. Returns ``[C] + [S1]*(N-1)``."""
    X = _prepare(V_next, r_t, nxt_t, p, gamma)
    q = _q_first(X, r_t[0], nxt_t, p, s1, a1)  # [A1, C, A.., S..]
    N = V_next.dim()
    q = q.movedim(1, N)  # [A1, A..(N-1), C, S..]
    q = q.reshape((-1,) + tuple(q.shape[N:]))
    return q.amax(0) if hard else torch.logsumexp(q, 0)


def _pull(values_at, pred_src: torch.Tensor, pred_w: torch.Tensor) -> torch.Tensor:
    """Transposed operator along one expert axis, as a gather:
    ``out[.., s', ..] = Σ_a Σ_k w[a, s', k] * values_at(src[a, s', k])``.

    ``values_at(src)`` with ``src`` ``[A1, S1]`` returns ``[A1, S1, ...]`` (the source
    values for action ``a`` at cell ``src[a, s']``)."""
    K = pred_src.shape[-1]
    total = None
    for k in range(K):
        v = values_at(pred_src[..., k])
        w = pred_w[..., k].reshape(tuple(pred_w.shape[:2]) + (1,) * (v.dim() - 2))
        term = (w * v).sum(0)
        total = term if total is None else total + term
    return total


def _forward_kernel(V_next, Vlse, logd, r_t, nxt_t, p, gamma, pred_src, pred_w, eye_src,
                    a_index):
    """One forward step.

    Args:
        V_next: ``[S1]*N`` value at t+1. Vlse: ``[S1]*N`` logsumexp part of ``V_t``.
        logd: ``[S1]*N`` log state distribution at t (``-inf`` where zero).
        pred_src, pred_w: ``[N?]`` no — ``[A1, S1, K]`` predecessor table of an expert.
        eye_src: ``[A1, S1]`` identity cells; a_index: ``[A1, S1]`` action index.

    Returns:
        (rho1 ``[A1, S1]`` expert-1 marginal, Z ``[A1]*(N-1) + [S1]*N``: the state-action
        distribution with expert 1's transition applied, other experts' actions kept).
    """
    X = _prepare(V_next, r_t, nxt_t, p, gamma)
    N = V_next.dim()
    shift = logd - Vlse  # [S1]*N ; log(d) - V, so rho = exp(Q + shift)

    def rho_at(src):
        q = _q_first(X, r_t[0], nxt_t, p, src, a_index)  # [A1, S1, A.., S2..]
        sh = shift[src]  # [A1, S1, S2..]
        sh = sh.reshape(tuple(sh.shape[:2]) + (1,) * (N - 1) + tuple(sh.shape[2:]))
        return torch.exp(q + sh)

    rho_self = rho_at(eye_src)  # [A1, S1, A.., S..]
    # (sum(dim=()) would reduce *every* axis, hence the guard for one expert)
    rho1 = rho_self.sum(dim=tuple(range(2, rho_self.dim()))) if rho_self.dim() > 2 else rho_self
    Z = _pull(rho_at, pred_src, pred_w)  # [S1', A.., S2..]
    return rho1, Z.movedim(0, N - 1)  # [A.., S1', S2..]


# ---------------------------------------------------------------------------- solution
@dataclass
class SoftBellmanSolution:
    """Result of :meth:`FactoredSoftBellman.solve`.

    Attributes:
        V: ``[T+1, S1, .., S1]`` values (``V[T] = 0``), in the solver dtype.
        state_occupancy: ``[S1]*N`` float64, ``Σ_t γ^t d_t(s)`` (None if not computed).
        local_occupancy: ``[N, S1, A1]`` float64, ``Σ_t γ^t ρ_t^i(s_i, a_i)`` — each
            expert's marginal of the discounted state-action occupancy.
        log_partition: ``Σ_s P0(s) V_0(s)``.
    """

    V: torch.Tensor
    reward: FactoredReward
    temperature: float
    solver: FactoredSoftBellman = field(repr=False)
    state_occupancy: torch.Tensor | None = None
    local_occupancy: torch.Tensor | None = None

    @property
    def log_partition(self) -> float:
        p0 = self.solver.model.initial_distribution().to(self.V.device)
        return float((p0 * self.V[0].double()).sum())

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
        temperature 0 the policy is uniform over the maximising joint actions."""
        q = self.q_values_at(t, cells).double()
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
        dtype: value dtype (float32 is the fast default; float64 for checks).
        compile: ``True``/``False``/``"auto"`` — fuse the ``S·A`` stages with
            ``torch.compile``; ``"auto"`` compiles above 5M pairs.
        chunk_cells: expert-1 cells per chunk on the eager path (bounds memory).
        progress: show a tqdm bar over time steps.
    """

    def __init__(self, *, model: TabularGridModel, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32, compile: bool | str = "auto",
                 chunk_cells: int = 9, progress: bool = False) -> None:
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
        self.eye_src = torch.arange(S1, device=dev).unsqueeze(0).expand(A1, S1).contiguous()
        self.pred_src, self.pred_w = self._predecessors()
        self._bwd = self._fwd = None
        if self.use_compile:
            self._bwd = torch.compile(_backward_kernel, dynamic=False)
            self._fwd = torch.compile(_forward_kernel, dynamic=False)

    def _predecessors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``[A1, S1, K]`` cells that reach each cell under each action, and their
        probabilities (padded with weight 0)."""
        P1 = self.model.expert_transition()  # [S1, A1, S1']
        nz = P1 > 0
        K = int(nz.sum(0).max())
        S1, A1 = self.model.n_cells, self.model.n_actions
        src = torch.zeros(A1, S1, K, dtype=torch.int64)
        w = torch.zeros(A1, S1, K, dtype=torch.float64)
        for a in range(A1):
            for s2 in range(S1):
                srcs = torch.nonzero(nz[:, a, s2]).flatten()
                src[a, s2, :len(srcs)] = srcs
                w[a, s2, :len(srcs)] = P1[srcs, a, s2]
        return src.to(self.device), w.to(self.device, self.dtype)

    # ---------------------------------------------------------------- reward handling
    def _tables(self, reward: FactoredReward, temperature: float):
        m = self.model
        scale = 1.0 if temperature == 0.0 else 1.0 / temperature
        local = reward.local
        if tuple(local.shape) != (m.n_experts, m.n_cells, m.n_actions):
            raise ValueError(f"reward.local must be [{m.n_experts}, {m.n_cells}, "
                             f"{m.n_actions}], got {tuple(local.shape)}.")
        if torch.isnan(local).any() or (reward.joint is not None and torch.isnan(reward.joint).any()):
            raise ValueError("The reward contains NaN; check the weights (ω_r, λ, ω_c).")
        r_t = (local * scale).transpose(1, 2).to(self.device, self.dtype).contiguous()
        g = None
        if reward.joint is not None:
            g = (reward.joint * scale).reshape(m.state_shape).to(self.device, self.dtype)
        return r_t, g

    # ------------------------------------------------------------------------ backward
    def _backward_step(self, V_next, r_t, hard: bool) -> torch.Tensor:
        S1, A1 = self.model.n_cells, self.model.n_actions
        gamma = self.model.gamma
        if self.use_compile:
            return self._bwd(V_next, r_t, self.nxt_t, self.p, gamma, self.eye_src,
                             self.a_index, hard)
        out = torch.empty_like(V_next)
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            out[c] = _backward_kernel(V_next, r_t, self.nxt_t, self.p, gamma,
                                      self.eye_src[:, c], self.a_index[:, c], hard)
        return out

    def solve(self, reward: FactoredReward, *, temperature: float = 1.0,
              forward: bool = True) -> SoftBellmanSolution:
        """Backward (and optionally forward) pass for ``reward``.

        Args:
            reward: per-expert tables and joint-state term; ``-inf`` marks forbidden
                pairs (hard constraints).
            temperature: ``τ > 0`` soft-optimal; ``0`` hard-max DP (no forward pass).
            forward: also compute occupancies (needs ``τ > 0``).
        """
        if not (temperature >= 0.0 and math.isfinite(temperature)):
            raise ValueError(f"temperature must be a finite number >= 0, got {temperature!r}.")
        if forward and temperature == 0.0:
            raise ValueError("The forward pass needs a soft policy: use temperature > 0 "
                             "(or forward=False for the hard-max DP).")
        m = self.model
        hard = temperature == 0.0
        r_t, g = self._tables(reward, temperature)
        T = m.horizon
        V = torch.zeros((T + 1,) + m.state_shape, dtype=self.dtype, device=self.device)
        steps = range(T - 1, -1, -1)
        if self.progress:
            from tqdm.auto import tqdm
            steps = tqdm(steps, desc="backward", leave=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for t in steps:
                v = self._backward_step(V[t + 1], r_t, hard)
                V[t] = v if g is None else v + g
        if not hard and temperature != 1.0:
            V *= temperature
        sol = SoftBellmanSolution(V=V, reward=reward, temperature=float(temperature), solver=self)
        if forward:
            self._forward(sol, r_t, g)
        return sol

    # ------------------------------------------------------------------------- forward
    def _forward(self, sol: SoftBellmanSolution, r_t, g) -> None:
        m = self.model
        N, T, gamma = m.n_experts, m.horizon, m.gamma
        tau = sol.temperature
        V = sol.V if tau == 1.0 else sol.V / tau
        d = m.initial_distribution().to(self.device, self.dtype)
        occ_state = torch.zeros(m.state_shape, dtype=torch.float64, device=self.device)
        occ_local = torch.zeros(N, m.n_actions, m.n_cells, dtype=torch.float64,
                                device=self.device)
        steps = range(T)
        if self.progress:
            from tqdm.auto import tqdm
            steps = tqdm(steps, desc="forward", leave=False)
        for t in steps:
            disc = gamma**t
            occ_state += disc * d
            Vlse = V[t] if g is None else V[t] - g
            logd = torch.where(d > 0, torch.log(d), torch.full_like(d, -math.inf))
            # States that cannot be occupied (V = -inf under hard constraints) have d = 0.
            Vlse = torch.where(torch.isfinite(Vlse), Vlse, torch.zeros_like(Vlse))
            rho1, Z = self._forward_step(V[t + 1], Vlse, logd, r_t)
            occ_local[0] += disc * rho1.double()
            # Remaining experts: their marginal from Z, then their transposed operator.
            for i in range(1, N):
                # Z: [A_i, .., A_N, S1, .., SN]; expert i's action is axis 0.
                k = Z.dim() - N
                keep = (0, k + i)
                occ_local[i] += disc * Z.double().sum(
                    dim=tuple(a for a in range(Z.dim()) if a not in keep))
                Zi = Z
                Z = _pull(lambda src, Zi=Zi, k=k, i=i: Zi.movedim(k + i, 1)[
                    self.a_index, src], self.pred_src, self.pred_w).movedim(0, k + i - 1)
            d = Z
        sol.state_occupancy = occ_state
        sol.local_occupancy = occ_local.transpose(1, 2).contiguous()  # [N, S1, A1]

    def _forward_step(self, V_next, Vlse, logd, r_t):
        S1 = self.model.n_cells
        args = (self.nxt_t, self.p, self.model.gamma)
        if self.use_compile:
            return self._fwd(V_next, Vlse, logd, r_t, *args, self.pred_src, self.pred_w,
                             self.eye_src, self.a_index)
        # Eager: chunk over the *target* cell of expert 1 (and its own marginal).
        rho1 = torch.zeros(self.model.n_actions, S1, dtype=self.dtype, device=self.device)
        Z = None
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            r1c, Zc = _forward_kernel(V_next, Vlse, logd, r_t, *args, self.pred_src[:, c],
                                      self.pred_w[:, c], self.eye_src[:, c],
                                      self.a_index[:, c])
            # rho1 of this chunk is indexed by the chunk's own cells (eye_src).
            rho1[:, c] = r1c
            if Z is None:
                Z = torch.empty(Zc.shape[:self.model.n_experts - 1] + (S1,) + Zc.shape[
                    self.model.n_experts:], dtype=Zc.dtype, device=Zc.device)
            Z.narrow(self.model.n_experts - 1, c.start, c.stop - c.start).copy_(Zc)
        return rho1, Z

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
        for i in range(N):  # axis 1+i: [stay, moves] -> actions
            U = U.movedim(1 + i, 0)
            U = self.p * U[1:] + (1 - self.p) * U[:1]
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
