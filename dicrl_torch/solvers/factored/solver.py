"""The factored soft-Bellman solver: tables of the model, validation, and the two passes
(:mod:`.backward`, :mod:`.forward`) put together."""

from __future__ import annotations

import math
import time
import warnings

import torch

from dicrl_torch.envs.grid import TabularGridModel
from dicrl_torch.features.base import EnvKind
from dicrl_torch.features.bases import FactoredReward
from dicrl_torch.solvers.factored.backward import backward_kernel, backward_pass
from dicrl_torch.solvers.factored.forward import (
    forward_kernel,
    forward_pass,
    pull_kernel,
    pull_tilted_kernel,
)
from dicrl_torch.solvers.factored.operators import mix
from dicrl_torch.solvers.factored.solution import SoftBellmanSolution

# Below this many state-action pairs the eager path is fast enough and compiling
# (seconds, once per shape) does not pay off.
COMPILE_MIN_PAIRS = 5_000_000
# Above this |V_t - c_t| (values about their per-step baseline, in units of τ), float32
# resolves policies worse than ~1e-3 per step: warn.
FLOAT32_VALUE_LIMIT = 1e4


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
        self._warned_value = 0.0  # the scale of the last float32 precision warning
        if self.use_compile:
            self._bwd = torch.compile(backward_kernel, dynamic=False)
            self._fwd = torch.compile(forward_kernel, dynamic=False)
            self._pull_compiled = torch.compile(pull_kernel, dynamic=False)
            self._pull_tilted_compiled = torch.compile(pull_tilted_kernel, dynamic=False)

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
                E[exp(V'/τ)]``, with occupancies of its tilted dynamics (package
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
        sync = torch.cuda.synchronize if self.device.type == "cuda" else (lambda: None)
        t0 = time.perf_counter()
        terminal = None
        if terminal_value is not None:
            if tuple(terminal_value.shape) != m.state_shape:
                raise ValueError(f"terminal_value must have shape {m.state_shape}, got "
                                 f"{tuple(terminal_value.shape)}.")
            if torch.isnan(terminal_value).any():
                raise ValueError("terminal_value contains NaN.")
            scale = 1.0 if temperature == 0.0 else 1.0 / temperature
            terminal = terminal_value.to(self.device, self.dtype) * scale
        trajectory = backup == "trajectory"
        V, centres, L1 = backward_pass(self, r_t, g, terminal, hard=hard, trajectory=trajectory,
                                       keep_l1=forward)
        sync()
        t1 = time.perf_counter()
        if self.dtype == torch.float32:
            self._check_scale(V)
        sol = SoftBellmanSolution(values=V, baseline=self._baseline(centres), reward=reward,
                                  temperature=float(temperature), solver=self, backup=backup)
        sol.timings["backward_s"] = t1 - t0
        if forward:
            sol.state_occupancy, sol.local_occupancy = forward_pass(
                self, V, centres, r_t, g, L1, trajectory)
            sync()
            sol.timings["forward_s"] = time.perf_counter() - t1
        if not hard and temperature != 1.0:
            V *= temperature
            sol.baseline *= temperature
        return sol

    def _baseline(self, centres: torch.Tensor) -> torch.Tensor:
        """``[T+1]`` float64 on the CPU: ``c_t = m_t + γ c_{t+1}`` from the backward pass's
        centres ``m`` ``[T+1]``, so that ``V_t = v_t + c_t``."""
        m = centres.cpu().tolist()
        gamma = self.model.gamma
        c = [0.0] * len(m)
        c[-1] = m[-1]
        for t in range(len(m) - 2, -1, -1):
            c[t] = m[t] + gamma * c[t + 1]
        return torch.tensor(c, dtype=torch.float64)

    def _check_scale(self, V: torch.Tensor) -> None:
        """Warn when float32 cannot resolve the values ``V`` ``[T+1] + [S1]*N`` (relative to
        their per-step baseline, in units of ``τ``: what the kernels compute with)."""
        # One pass without a copy; states with no allowed action hold -inf and are masked
        # out only then.
        lo, hi = torch.aminmax(V)
        if lo == -math.inf:
            lo, hi = torch.aminmax(V.masked_fill(V == -math.inf, 0.0))
        v_max = max(abs(float(lo)), abs(float(hi)))
        # Again only when the scale has doubled since: a training run solves hundreds of
        # times at about the same scale, and one line says it.
        if v_max > max(FLOAT32_VALUE_LIMIT, 2.0 * self._warned_value):
            # float32 resolves V to ~|V| * 6e-8; beyond this, policies (exp(Q - V)) lose
            # per-step accuracy of order 1e-3 or worse and occupancies drift. The baseline
            # takes out the part of V common to all states, so what is left is the
            # spread of the values over the states: the reward's scale times the steps
            # it takes to reach the best states.
            self._warned_value = v_max
            warnings.warn(
                f"|V_t - c_t| reaches {v_max:.3g} (values about their per-step baseline, in "
                f"units of the temperature): float32 cannot resolve the policy accurately "
                f"at this scale; use dtype=torch.float64 (or smaller weights). Repeated "
                f"only if it doubles.", RuntimeWarning, stacklevel=3)

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
        Vn, base = sol.values[t + 1], float(sol.baseline[t + 1])
        if tau not in (0.0, 1.0):
            Vn, base = Vn / tau, base / tau
        B = cells.shape[0]
        # Candidate next cells per expert: [stay, move(a) for a in A1] -> [B, N, 1+A1].
        cand = torch.cat([cells.unsqueeze(-1), self.nxt_t.t()[cells]], -1)
        idx = [cand[:, i].reshape([B] + [1] * i + [A1 + 1] + [1] * (N - 1 - i))
               for i in range(N)]
        # The baseline joins in float64, which resolves it with the values about it.
        U = Vn[tuple(idx)].double() + base  # [B, (1+A1)^N]
        log_space = sol.backup == "trajectory"  # log E[exp V'] instead of E[V']
        for i in range(N):  # axis 1+i: [stay, moves] -> actions
            U = U.movedim(1 + i, 0)
            U = mix(U[1:], U[:1], self.p, log_space)
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
