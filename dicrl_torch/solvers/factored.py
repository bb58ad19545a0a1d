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
import time
import warnings
from dataclasses import dataclass, field

import torch

from dicrl_torch.envs.grid import TabularGridModel
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


def _q_first(X: torch.Tensor, r1_t: torch.Tensor, move_to: torch.Tensor, stay_at, p: float
             ) -> torch.Tensor:
    """Q (without the joint term) for every expert-1 action at a set of expert-1 cells.

    Args:
        X: ``_prepare(..)`` output, ``[A1]*(N-1) + [S1]*N``.
        r1_t: ``[A1, C]`` expert 1's reward at those cells.
        move_to: ``[A1, C]`` where each action's success leads.
        stay_at: the cells themselves: a ``slice`` (structured, cheap) or ``[A1, C]``.
        p: success probability.

    Returns:
        ``[A1, C] + [A1]*(N-1) + [S1]*(N-1)``.
    """
    k = (X.dim() - 1) // 2  # N-1 action axes come first; expert 1's state axis is k
    Xm = X.movedim(k, 0)  # [S1, A.., S..] (a view)
    stay = Xm[stay_at]
    if isinstance(stay_at, slice):
        stay = stay.unsqueeze(0)
    q = p * Xm[move_to] + (1.0 - p) * stay
    return q + r1_t.reshape(tuple(r1_t.shape) + (1,) * (X.dim() - 1))


def _backward_kernel(V_next, r_t, nxt_t, p, gamma, cells: slice, hard: bool):
    """Backward step for the expert-1 cells ``cells``.

    Returns:
        ``(L1, V)``: ``L1`` ``[A1, C] + [S1]*(N-1)`` logsumexp (or max) over the other
        experts' actions for each expert-1 action, and ``V`` ``[C] + [S1]*(N-1)`` the
        reduction of ``L1`` over expert 1's action (no joint term).
    """
    X = _prepare(V_next, r_t, nxt_t, p, gamma)
    q = _q_first(X, r_t[0][:, cells], nxt_t[:, cells], cells, p)  # [A1, C, A.., S..]
    N = V_next.dim()
    others = tuple(range(2, N + 1))
    if hard:
        L1 = q.amax(others) if others else q
        return L1, L1.amax(0)
    L1 = _logsumexp(q, others) if others else q
    return L1, _logsumexp(L1, (0,))


def _forward_kernel(V_next, shift, r_t, nxt_t, p, gamma, cells: slice, w_self, move_src,
                    move_nxt, move_r, w_move):
    """Expert 1's transposed operator applied to ``ρ_t = d_t π_t`` (other experts'
    actions kept), as a pull: each target cell in ``cells`` gathers its self term
    (structured) and its move predecessors (one table lookup each).

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
        log_partition: ``Σ_s P0(s) V_0(s)``.
    """

    V: torch.Tensor
    reward: FactoredReward
    temperature: float
    solver: FactoredSoftBellman = field(repr=False)
    state_occupancy: torch.Tensor | None = None
    local_occupancy: torch.Tensor | None = None
    timings: dict[str, float] = field(default_factory=dict)

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
        dtype: value dtype, ``torch.float32`` (fast default) or ``torch.float64``
            (checks, extreme weights); the names ``"float32"``/``"float64"`` work too.
        compile: ``True``/``False``/``"auto"`` — fuse the ``S·A`` stages with
            ``torch.compile``; ``"auto"`` compiles above 5M pairs.
        chunk_cells: expert-1 cells per chunk on the eager path (bounds memory).
        progress: show a tqdm bar over time steps.
    """

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
        if self.use_compile:
            self._bwd = torch.compile(_backward_kernel, dynamic=False)
            self._fwd = torch.compile(_forward_kernel, dynamic=False)
            self._pull_compiled = torch.compile(_pull_kernel, dynamic=False)

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
    def _backward_step(self, V_next, r_t, hard: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L1 [A1] + [S1]*N, Vlse [S1]*N)`` for one step (see _backward_kernel)."""
        S1 = self.model.n_cells
        gamma = self.model.gamma
        if self.use_compile:
            # A fresh tensor, not a view into V: views at other offsets would recompile.
            return self._bwd(V_next.clone(), r_t, self.nxt_t, self.p, gamma, slice(None), hard)
        L1 = torch.empty((self.model.n_actions,) + tuple(V_next.shape), dtype=V_next.dtype,
                         device=V_next.device)
        V = torch.empty_like(V_next)
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            L1[:, c], V[c] = _backward_kernel(V_next, r_t, self.nxt_t, self.p, gamma, c, hard)
        return L1, V

    def solve(self, reward: FactoredReward, *, temperature: float = 1.0,
              forward: bool = True, terminal_value: torch.Tensor | None = None
              ) -> SoftBellmanSolution:
        """Backward (and optionally forward) pass for ``reward``.

        Args:
            reward: per-expert tables and joint-state term; ``-inf`` marks forbidden
                pairs (hard constraints).
            temperature: ``τ > 0`` soft-optimal; ``0`` hard-max DP (no forward pass).
            forward: also compute occupancies (needs ``τ > 0``).
            terminal_value: ``V_T`` ``[S1]*N`` (default 0). Nothing is scored at the
                last state ``s_T``, so hard constraints on states must also be put
                here (``-inf``), or the last move may enter a forbidden state.
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
                l1, v = self._backward_step(V[t + 1], r_t, hard)
                V[t] = v if g is None else v + g
                if L1 is not None:
                    L1[t] = l1
        if not hard and temperature != 1.0:
            V *= temperature
        sync()
        t1 = time.perf_counter()
        if self.dtype == torch.float32:
            finite = V[torch.isfinite(V)]
            v_max = float(finite.abs().max()) if finite.numel() else 0.0
            if v_max > FLOAT32_VALUE_LIMIT:
                # float32 resolves V to ~|V| * 6e-8; beyond this, policies (exp(Q - V))
                # lose per-step accuracy of order 1e-3 or worse and occupancies drift.
                warnings.warn(
                    f"|V| reaches {v_max:.3g}: float32 cannot resolve the policy accurately "
                    f"at this scale; use dtype=torch.float64 (or smaller weights).",
                    RuntimeWarning, stacklevel=2)
        sol = SoftBellmanSolution(V=V, reward=reward, temperature=float(temperature), solver=self)
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
            Z = self._forward_step(V[t + 1], shift, r_t).movedim(0, N - 1)  # [A.., S..]
            for i in range(1, N):  # Z: [A_i, .., A_N, S1, .., SN]
                k = Z.dim() - N
                # float32 partial sums, float64 accumulation over time
                occ_local[i] += disc * Z.sum(
                    dim=tuple(a for a in range(Z.dim()) if a not in (0, k + i))).double()
                Z = self._pull(Z.movedim(k + i, 1)).movedim(0, k + i - 1)
            d = Z.contiguous()  # a permuted view otherwise: odd strides recompile kernels
        sol.state_occupancy = occ_state
        sol.local_occupancy = occ_local.transpose(1, 2).contiguous()  # [N, S1, A1]

    def _pull(self, Y: torch.Tensor) -> torch.Tensor:
        """``[A1, S1, ...]`` -> ``[S1', ...]``: see :func:`_pull_kernel`."""
        f = self._pull_compiled if self.use_compile else _pull_kernel
        return f(Y.contiguous(), self.w_self, self.a_index, self.move_src, self.w_move)

    def _forward_step(self, V_next, shift, r_t):
        """``Z`` ``[S1'] + [A1]*(N-1) + [S1]*(N-1)``: ρ_t through expert 1's operator."""
        S1 = self.model.n_cells
        move_r = r_t[0][self.a_index.unsqueeze(0), self.move_src]  # [K, A1, S1]
        args = (self.nxt_t, self.p, self.model.gamma)
        if self.use_compile:
            return self._fwd(V_next.clone(), shift, r_t, *args, slice(None), self.w_self,
                             self.move_src, self.move_nxt, move_r, self.w_move)
        # Eager: chunk over the *target* cells of expert 1 (the self term needs no
        # gather, so its cells are a slice of the full tables).
        parts = []
        for c0 in range(0, S1, self.chunk_cells):
            c = slice(c0, min(S1, c0 + self.chunk_cells))
            parts.append(_forward_kernel(
                V_next, shift, r_t, *args, c, self.w_self[:, c], self.move_src[:, :, c],
                self.move_nxt[:, :, c], move_r[:, :, c], self.w_move[:, :, c]))
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
