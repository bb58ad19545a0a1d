"""Feature bases of any continuous multi-agent environment.

A basis here is an ``nn.Module`` without trainable parameters of
``env_kind = "continuous"`` mapping joint states ``[..., N, d_s]`` (per agent its state
or observation, e.g. ``x, y, vx, vy``; numpy or torch, any batch shape) to features
``[..., l]`` in ``[0, max_value]`` (the paper's ``φ ∈ [0, d]^l``), checked on every
call. They are functions of the state only (actions ``[..., N, d_a]`` may be passed and
are checked, not used), so they evaluate solver rollouts and demonstrations alike
(:class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations` ``states``).

- :class:`ContinuousFeatureBasis`: the shared input and output checks; subclass it and
  implement :meth:`~ContinuousFeatureBasis.compute`.
- :class:`ModuleBasis`: any frozen ``nn.Module`` (a pretrained or random network), its
  weights optionally read from a ``state_dict`` file with ``weights_only=True``;
  :func:`bounded_mlp` builds a seeded MLP whose outputs lie in ``[0, max_value]``.
- :class:`RandomFourierBasis`: seeded random Fourier features of the joint state.
- :class:`PositionCellBasis`: counts of agents per cell of a regular grid over a
  rectangular arena plus a proximity indicator, with a ground truth
  (:meth:`~PositionCellBasis.true_constraints`): a cost basis for arenas with disc
  obstacles and a minimum separation (e.g. a constrained MPE ``simple_spread``).
"""

from __future__ import annotations

import itertools
import os
import pickle
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dicrl_torch.checks import check_int, check_positive
from dicrl_torch.features.base import EnvKind
from dicrl_torch.io import atomic_write

__all__ = [
    "ContinuousFeatureBasis",
    "ModuleBasis",
    "PositionCellBasis",
    "RandomFourierBasis",
    "ScaledSigmoid",
    "bounded_mlp",
    "load_module_weights",
]


def _optional_int(name: str, value: Any) -> int | None:
    return None if value is None else check_int(name, value)


def check_position_columns(position_columns: Sequence[int],
                           state_dim: int | None) -> tuple[int, ...]:
    """``position_columns``, the columns ``(x, y)`` of a position in an agent's state, as
    two distinct non-negative ints below ``state_dim`` (when given).

    Raises:
        ValueError: anything else, naming the value.
    """
    cols = tuple(position_columns)
    if len(cols) != 2 or any(isinstance(c, bool) or not isinstance(c, int | np.integer)
                             or c < 0 for c in cols) or cols[0] == cols[1]:
        raise ValueError(f"position_columns must be two distinct non-negative ints "
                         f"(the x and y components of a state), got {position_columns!r}.")
    if state_dim is not None and max(cols) >= state_dim:
        raise ValueError(f"position_columns {cols} do not fit state_dim={state_dim}.")
    return tuple(int(c) for c in cols)


def check_bounds(bounds: Any) -> np.ndarray:
    """``bounds`` ``((x_lo, x_hi), (y_lo, y_hi))`` as a ``[2, 2]`` float64 array, finite,
    with ``lo < hi``."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 2) or not np.isfinite(b).all() or not (b[:, 0] < b[:, 1]).all():
        raise ValueError(f"bounds must be ((x_lo, x_hi), (y_lo, y_hi)) with lo < hi, got "
                         f"{bounds!r}.")
    return b


class ContinuousFeatureBasis(nn.Module):
    """Base class of the bases over joint states ``[..., N, d_s]`` (a
    :class:`~dicrl_torch.features.base.Basis` of kind ``"continuous"``).

    Subclasses set ``self.names`` (one label per feature), ``self.max_value`` and, where
    they fix them, ``self.n_agents`` / ``self.state_dim`` / ``self.action_dim`` (None:
    any), register their constants as buffers and implement :meth:`compute`. A feature
    that belongs to one agent is named ``f"{agent_prefix}{i}/..."`` (:meth:`agent_shares`).
    :meth:`forward` checks the input (float, finite, shape) and that the output has
    width :attr:`dim` and lies in ``[0, max_value]``; :attr:`fix_hint` says in that
    message how to repair a basis whose values leave the range.
    """

    max_value: float = 1.0
    names: list[str]
    # experiments/config_checks.py refuses a basis whose kind is not the configured env's.
    env_kind: EnvKind = "continuous"
    game: str | None = None
    """The one game whose geometry the basis is built on (e.g. ``"drones"``), or None:
    any game of its states' shape. Config checks and the SAC tasks refuse it elsewhere."""
    n_agents: int | None = None
    state_dim: int | None = None
    action_dim: int | None = None
    fix_hint: str = "rescale the basis or raise its max_value"
    agent_prefix: str = "agent"
    """Feature names ``f"{agent_prefix}{i}/..."`` are agent ``i``'s own."""

    @property
    def dim(self) -> int:
        """Number of features ``l``."""
        return len(self.names)

    @property
    def label(self) -> str:
        """How messages name the basis."""
        return type(self).__name__

    def compute(self, states: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """``[..., N, d_s]`` checked states to ``[..., l]`` features."""
        raise NotImplementedError

    def agent_shares(self, n_agents: int | None = None) -> torch.Tensor:
        """``[l, N]`` float64: how much of each feature's reward belongs to each agent.
        A feature named ``f"{agent_prefix}{i}/..."`` is agent ``i``'s alone (a one-hot
        row); any other (e.g. a proximity, or a cell count of the whole team) is shared
        equally (``1 / N`` each). Rows sum to 1, so per-agent rewards (a per-agent critic,
        :mod:`dicrl_torch.solvers.sac.decomposed`) add up to the joint reward.

        Args:
            n_agents: ``N``; default the basis's own ``n_agents`` (one of the two must be
                known, and they must agree).
        """
        n = self.n_agents if n_agents is None else check_int("n_agents", n_agents)
        if n is None or (self.n_agents is not None and n != self.n_agents):
            raise ValueError(f"{self.label}: agent_shares needs the number of agents: pass "
                             f"n_agents (the basis was built for n_agents={self.n_agents}, "
                             f"asked for {n_agents}).")
        shares = torch.full((self.dim, n), 1.0 / n, dtype=torch.float64)
        for j, name in enumerate(self.names):
            owner = name.split("/", 1)[0].removeprefix(self.agent_prefix)
            if owner.isdigit():
                if int(owner) >= n:
                    raise ValueError(f"{self.label}: feature {name!r} names an agent beyond "
                                     f"the {n} of the game; rename it.")
                shares[j] = 0.0
                shares[j, int(owner)] = 1.0
        return shares

    # Optional abilities, declared here with their generic versions so that callers call
    # them on any basis instead of probing for them; a basis overrides what it does
    # faster (numpy_features, dot) or at all (dilated, cell_rectangles).
    dilatable: bool = False
    """Whether :meth:`dilated` grows the features by a margin (a SAC task's
    ``final_margin``, the drone planner's); a basis that overrides it sets this."""

    def numpy_features(self, states: np.ndarray) -> np.ndarray:
        """``[..., l]`` :meth:`compute` of numpy joint states ``[..., N, d_s]``, without
        :meth:`forward`'s checks (a planner's batches). Here through torch; a basis with a
        faster numpy path overrides it, equal bit for bit."""
        return self.compute(torch.as_tensor(states)).numpy()

    def dot(self, states: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """``[...]`` :meth:`numpy_features` of joint states ``[..., N, d_s]`` times
        ``weights [l]``; a basis that looks the weights up without building the
        ``[..., l]`` features overrides it, equal bit for bit."""
        return self.numpy_features(states) @ weights

    def dilated(self, margin: float) -> ContinuousFeatureBasis:
        """The same features, each firing within ``margin`` of where it fires here; only
        a :attr:`dilatable` basis has them (cells that can be grown)."""
        raise NotImplementedError(f"{self.label} cannot be grown by a margin (its "
                                  f"dilatable is False).")

    def cell_rectangles(self) -> np.ndarray:
        """``[C, 4]`` float64 ``(x0, y0, x1, y1)`` of the cells its first ``C`` features
        count, for maps of learned constraints; ``[0, 4]`` here: no feature is a cell."""
        return np.zeros((0, 4))

    def forward(self, states: Any, actions: Any = None) -> torch.Tensor:
        """Features of joint states.

        Args:
            states: ``[..., N, d_s]`` float (numpy or torch), finite.
            actions: optional ``[..., N, d_a]`` float; checked, unused (state features).

        Returns:
            ``[..., l]`` features in ``[0, max_value]``, in the dtype of ``states``
            (float64 for numpy input), on the basis's device.

        Raises:
            ValueError: malformed input, or features of the wrong width or outside
                ``[0, max_value]`` (naming the basis, the bad values and the fix).
        """
        states = self._check(states, "states", self.n_agents, self.state_dim)
        if actions is not None:
            actions = self._check(actions, "actions", states.shape[-2], self.action_dim)
            if actions.shape[:-1] != states.shape[:-1]:
                raise ValueError(
                    f"{self.label}: actions of shape {tuple(actions.shape)} do not match "
                    f"states of shape {tuple(states.shape)}; give one action [..., N, d_a] "
                    f"per state [..., N, d_s].")
        phi = self.compute(states)
        self._validate(phi, states.shape[:-2])
        return phi.to(states.dtype)

    def _device(self) -> torch.device | None:
        t = next(itertools.chain(self.buffers(), self.parameters()), None)
        return None if t is None else t.device

    def _check(self, x: Any, name: str, n: int | None, d: int | None) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            a = np.asarray(x)
            if not np.issubdtype(a.dtype, np.floating):
                raise ValueError(f"{self.label}: {name} must be a float array, got dtype "
                                 f"{a.dtype}; convert with .astype(np.float64).")
            # torch cannot wrap a read-only array (e.g. demonstration fields): copy.
            x = torch.from_numpy(a if a.flags.writeable else a.copy())
        if not x.is_floating_point():
            raise ValueError(f"{self.label}: {name} must be a float tensor, got dtype "
                             f"{x.dtype}; convert with .double().")
        want = f"[..., {'N' if n is None else n}, {'d' if d is None else d}]"
        if x.ndim < 2 or (n is not None and x.shape[-2] != n) \
                or (d is not None and x.shape[-1] != d):
            raise ValueError(
                f"{self.label}: {name} must have shape {want} (agents, then per agent "
                f"components), got {tuple(x.shape)}; this basis was built for "
                f"n_agents={self.n_agents}, {name[:-1]}_dim={d}.")
        if not torch.isfinite(x).all():
            first = tuple(int(v) for v in torch.nonzero(~torch.isfinite(x))[0])
            raise ValueError(f"{self.label}: {name} contain NaN or inf values (first at "
                             f"index {first}); mask padding before computing features.")
        device = self._device()
        return x if device is None else x.to(device)

    def _validate(self, phi: Any, batch: torch.Size) -> None:
        if not isinstance(phi, torch.Tensor):
            raise TypeError(f"{self.label} produced a {type(phi).__name__}, not a tensor "
                            f"of features [..., {self.dim}].")
        if tuple(phi.shape) != (*batch, self.dim):
            raise ValueError(
                f"{self.label} produced features of shape {tuple(phi.shape)} for states of "
                f"batch shape {tuple(batch)}, expected {(*batch, self.dim)}: "
                f"{phi.shape[-1] if phi.ndim else 0} features per state where dim = "
                f"{self.dim}.")
        if phi.numel() == 0:
            return
        # Round-off of a float32 network scaled by max_value must not count as a breach.
        tol = max(1e-9, 4 * torch.finfo(phi.dtype).eps * max(1.0, self.max_value))
        bad = ~torch.isfinite(phi) | (phi < 0) | (phi > self.max_value + tol)
        if bad.any():
            where = torch.nonzero(bad)
            idx = tuple(int(v) for v in where[0])
            finite = phi[torch.isfinite(phi)]
            span = (f"min {float(finite.min()):.4g}, max {float(finite.max()):.4g}"
                    if finite.numel() else "no finite value")
            n_nan = int((~torch.isfinite(phi)).sum())
            raise ValueError(
                f"{self.label} features leave [0, {self.max_value}]: {len(where)} of "
                f"{phi.numel()} values are outside (first {float(phi[idx]):.4g} at index "
                f"{idx}, feature {self.names[idx[-1]]!r}; {span}; {n_nan} NaN/inf). The "
                f"paper assumes bounded non-negative features (φ ∈ [0, d]^l): "
                f"{self.fix_hint}.")


# ============================================================================ modules
class ScaledSigmoid(nn.Module):
    """``max_value * sigmoid(x)``: a network head whose outputs lie in
    ``[0, max_value]``."""

    def __init__(self, max_value: float = 1.0) -> None:
        super().__init__()
        self.max_value = check_positive("max_value", max_value)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.max_value * torch.sigmoid(x)

    def extra_repr(self) -> str:
        return f"max_value={self.max_value}"


def bounded_mlp(in_features: int, out_features: int, hidden: Sequence[int] = (64,), *,
                max_value: float = 1.0, seed: int = 0) -> nn.Sequential:
    """A seeded MLP ``in_features -> hidden... (tanh) -> out_features`` ending in
    :class:`ScaledSigmoid`, so its outputs lie in ``[0, max_value]``: a ready module for
    :class:`ModuleBasis` (``in_features = N * d_s``).

    The weights are drawn from a ``torch.Generator`` seeded with ``seed`` (PyTorch's
    default uniform ``±1/sqrt(fan_in)`` init), never from the global generator.
    """
    widths = [check_int("in_features", in_features),
              *(check_int("hidden", h) for h in hidden),
              check_int("out_features", out_features)]
    g = torch.Generator().manual_seed(int(seed))
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(widths)):
        # skip_init: nn.Linear's own init would draw from the global generator.
        lin = nn.utils.skip_init(nn.Linear, a, b)
        bound = 1.0 / np.sqrt(a)
        with torch.no_grad():
            lin.weight.copy_((torch.rand(b, a, generator=g) * 2 - 1) * bound)
            lin.bias.copy_((torch.rand(b, generator=g) * 2 - 1) * bound)
        layers.append(lin)
        if i < len(widths) - 2:
            layers.append(nn.Tanh())
    layers.append(ScaledSigmoid(max_value))
    return nn.Sequential(*layers)


def load_module_weights(module: nn.Module, path: str | os.PathLike[str]) -> nn.Module:
    """Load the ``state_dict`` at ``path`` into ``module`` (strictly) with
    ``torch.load(..., weights_only=True)``: a file holding a pickled module or other
    objects is refused, never unpickled.

    Returns:
        ``module``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a ``state_dict`` of tensors, or it does not fit
            ``module`` (naming the file and the fix).
    """
    path = Path(path)
    how = "save it with torch.save(module.state_dict(), path) (or ModuleBasis.save_weights)"
    if not path.is_file():
        raise FileNotFoundError(f"No module weights file '{path}': it does not exist or is "
                                f"not a file; {how}, or fix the path.")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as e:
        raise ValueError(
            f"module weights file '{path}' cannot be read with weights_only=True "
            f"({type(e).__name__}); it must hold a state_dict (a dict of tensors), which is "
            f"all that is ever loaded, never a pickled module: {how}.") from e
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor)
                                                 for v in state.values()):
        raise ValueError(f"module weights file '{path}' holds a {type(state).__name__}, not "
                         f"a state_dict of tensors; {how}.")
    try:
        module.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(
            f"module weights file '{path}' does not fit the module "
            f"{type(module).__name__} ({e}); build the module with the architecture the "
            f"weights were saved from (the same module_factory and sizes).") from e
    return module


class ModuleBasis(ContinuousFeatureBasis):
    """Wrap any frozen ``nn.Module`` as a basis: joint states ``[..., N, d_s]``,
    flattened per sample to ``[B, N * d_s]``, go through the module to ``[B, l]``
    features, reshaped to ``[..., l]`` (the continuous counterpart of the grid's
    :class:`~dicrl_torch.features.bases.FrozenModuleBasis`).

    The module is frozen (``requires_grad_(False)``, and kept in eval mode even when the
    basis is put in train mode, so dropout or batch norm never change the features),
    runs in its parameters' dtype (float32 unless converted) and its output is checked
    on every call: width ``dim``, every value in ``[0, max_value]``, no NaN. End the
    network with ``ScaledSigmoid(max_value)`` (:func:`bounded_mlp` does).

    From Hydra, ``_target_: dicrl_torch.features.continuous.ModuleBasis`` with a nested
    ``module`` (e.g. ``_target_: dicrl_torch.features.continuous.bounded_mlp``), ``dim``
    and optionally ``weights`` (a ``state_dict`` file).

    Args:
        module: the network, input width ``N * d_s``, output width ``dim``.
        dim: the number of features ``l`` the module returns.
        max_value: the bound ``d`` of every output.
        n_agents, state_dim: when given, inputs must have this ``N`` / ``d_s``.
        weights: optional ``state_dict`` file loaded into ``module`` first
            (:func:`load_module_weights`, ``weights_only=True``).
        names: ``dim`` feature labels (default ``f0, f1, ...``).
    """

    def __init__(self, *, module: nn.Module, dim: int, max_value: float = 1.0,
                 n_agents: int | None = None, state_dim: int | None = None,
                 weights: str | os.PathLike[str] | None = None,
                 names: Sequence[str] | None = None) -> None:
        super().__init__()
        if not isinstance(module, nn.Module):
            raise TypeError(f"ModuleBasis: module must be an nn.Module, got "
                            f"{type(module).__name__}; build the network first (or use "
                            f"ModuleBasis.from_file(path, module_factory, ...)).")
        dim = check_int("dim", dim)
        self.max_value = check_positive("max_value", max_value)
        self.n_agents = _optional_int("n_agents", n_agents)
        self.state_dim = _optional_int("state_dim", state_dim)
        if weights is not None:
            load_module_weights(module, weights)
        self.net = module.requires_grad_(False).eval()
        self.names = [f"f{j}" for j in range(dim)] if names is None else [str(s) for s in names]
        if len(self.names) != dim:
            raise ValueError(f"ModuleBasis: names has {len(self.names)} labels but dim = {dim}; "
                             f"give one label per feature.")
        self.fix_hint = (f"end the network with ScaledSigmoid({self.max_value}) (a sigmoid "
                         f"scaled by max_value; bounded_mlp does), or build the basis with the "
                         f"max_value its outputs really have")

    @classmethod
    def from_file(cls, path: str | os.PathLike[str],
                  module_factory: Callable[[], nn.Module] | nn.Module,
                  **kwargs: Any) -> ModuleBasis:
        """A basis whose module is ``module_factory()`` (or the module itself) with the
        ``state_dict`` at ``path`` loaded with ``weights_only=True``; ``kwargs`` (``dim``,
        ``max_value``, ...) go to the constructor."""
        module = module_factory if isinstance(module_factory, nn.Module) else module_factory()
        return cls(module=module, weights=path, **kwargs)

    def save_weights(self, path: str | os.PathLike[str]) -> Path:
        """Write the module's ``state_dict`` to ``path`` atomically, for
        :meth:`from_file` / ``weights=``."""
        state = {k: v.detach().cpu() for k, v in self.net.state_dict().items()}
        return atomic_write(path, lambda f: torch.save(state, f))

    @property
    def label(self) -> str:
        return f"ModuleBasis({type(self.net).__name__})"

    def train(self, mode: bool = True) -> ModuleBasis:
        super().train(mode)
        self.net.eval()  # a frozen feature map: never dropout or batch-norm updates
        return self

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        batch = states.shape[:-2]
        x = states.reshape(-1, states.shape[-2] * states.shape[-1])
        p = next(itertools.chain(self.net.parameters(), self.net.buffers()), None)
        dtype = p.dtype if p is not None and p.is_floating_point() else states.dtype
        try:
            with torch.no_grad():
                out = self.net(x.to(dtype))
        except RuntimeError as e:
            raise ValueError(
                f"{self.label} failed on input [B, {x.shape[-1]}] (N={states.shape[-2]} "
                f"agents x d_s={states.shape[-1]}, flattened per sample): {e}. The module's "
                f"input width must be N * d_s.") from e
        if not isinstance(out, torch.Tensor):
            raise TypeError(f"{self.label}: the module returned a {type(out).__name__}, "
                            f"not a tensor [B, {self.dim}].")
        if out.ndim != 2 or out.shape[0] != x.shape[0]:
            raise ValueError(f"{self.label}: the module returned shape {tuple(out.shape)} "
                             f"for input {tuple(x.shape)}; expected [B, dim] = "
                             f"{(x.shape[0], self.dim)}.")
        if out.shape[1] != self.dim:
            raise ValueError(f"{self.label}: the module returns {out.shape[1]} features per "
                             f"sample but dim = {self.dim}; set dim={out.shape[1]} (and as "
                             f"many names), or change the module's last layer.")
        return out.reshape(*batch, self.dim)


# ====================================================================== fixed bases
class RandomFourierBasis(ContinuousFeatureBasis):
    """Random Fourier features of the flattened joint state ``x = s.flatten() [N d_s]``:
    ``φ_j(s) = max_value (1 + cos(w_j·x + b_j)) / 2`` with ``w_j ~ N(0, diag(1/σ²))``
    and ``b_j ~ U[0, 2π)``, drawn once from ``seed`` (the same features on every device
    and in every process). ``l = n_features``, values in ``[0, max_value]``; they
    approximate a Gaussian kernel of length scale ``σ``.

    Args:
        n_agents, state_dim: ``N`` and ``d_s`` of the states (fixed: they size ``w``).
        n_features: ``l``.
        bandwidth: the length scale ``σ``: one number, or one per state component
            (``state_dim`` numbers, shared by the agents; e.g. metres for positions,
            m/s for velocities).
        seed: the only source of ``w`` and ``b``.
        max_value: the bound ``d``.
    """

    def __init__(self, *, n_agents: int, state_dim: int, n_features: int = 64,
                 bandwidth: float | Sequence[float] = 1.0, seed: int = 0,
                 max_value: float = 1.0) -> None:
        super().__init__()
        self.n_agents = check_int("n_agents", n_agents)
        self.state_dim = check_int("state_dim", state_dim)
        n_features = check_int("n_features", n_features)
        self.max_value = check_positive("max_value", max_value)
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}.")
        bw = np.atleast_1d(np.asarray(bandwidth, dtype=np.float64))
        if bw.shape not in ((1,), (self.state_dim,)):
            raise ValueError(f"bandwidth must be one number or {self.state_dim} (one per "
                             f"state component), got {len(bw)}.")
        for b in bw:
            check_positive("bandwidth", b)
        self.bandwidth = tuple(float(b) for b in bw)
        g = torch.Generator().manual_seed(int(seed))
        scale = torch.from_numpy(np.broadcast_to(bw, (self.state_dim,)).copy())
        scale = scale.repeat(self.n_agents)  # [N d_s], agent-major like flatten(-2)
        w = torch.randn(self.n_agents * self.state_dim, n_features, generator=g,
                        dtype=torch.float64) / scale[:, None]
        b = torch.rand(n_features, generator=g, dtype=torch.float64) * (2 * np.pi)
        # Non-persistent: the seed rebuilds them; buffers only to follow .to(device).
        self.register_buffer("frequencies", w, persistent=False)
        self.register_buffer("phases", b, persistent=False)
        self.names = [f"rff{j}" for j in range(n_features)]

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        x = states.flatten(-2)
        arg = x @ self.frequencies.to(states.dtype) + self.phases.to(states.dtype)
        return self.max_value * 0.5 * (1.0 + torch.cos(arg))


class PositionCellBasis(ContinuousFeatureBasis):
    """Counts of agents per cell of a regular grid over a rectangular arena, shared by
    the agents (like the grid world's shared indicator basis), plus one proximity
    indicator.

    Feature ``iy * nx + ix``, named ``cell(ix,iy)``, counts the agents whose position
    lies in ``[x_lo + ix w, x_lo + (ix+1) w) x [y_lo + iy h, y_lo + (iy+1) h)`` (``w, h``
    the cell sizes; a position outside the arena counts in the nearest border cell).
    The last, ``proximity``, is 1 when any two agents are closer than
    ``proximity_radius``. ``l = nx ny + 1``, ``max_value = N`` (all agents in one cell).

    With a ground truth (``obstacle_centre`` / ``obstacle_radius`` and ``min_distance``,
    here or passed to :meth:`true_constraints`) it is a
    :class:`~dicrl_torch.features.base.ConstraintBasis`.

    Args:
        n_agents: ``N``.
        bounds: ``((x_lo, x_hi), (y_lo, y_hi))`` of the arena (e.g. ``±arena_half_width``
            on both axes for the constrained MPE).
        proximity_radius: distance below which the proximity feature fires (the
            environment's least allowed distance between agents, ``min_distance``).
        n_per_axis: cells per axis: ``n`` (square grid) or ``(nx, ny)``.
        position_columns: the state components holding ``x`` and ``y``: two ints or a
            slice (default ``(0, 1)``, i.e. columns ``0:2``).
        state_dim: when given, inputs must have this ``d_s``.
        obstacle_centre, obstacle_radius, min_distance: the default ground truth of
            :meth:`true_constraints`.
    """

    def __init__(self, *, n_agents: int, bounds: Sequence[Sequence[float]],
                 proximity_radius: float, n_per_axis: int | Sequence[int] = 10,
                 position_columns: Sequence[int] | slice = (0, 1), state_dim: int | None = None,
                 obstacle_centre: Sequence[float] | Sequence[Sequence[float]] | None = None,
                 obstacle_radius: float | Sequence[float] | None = None,
                 min_distance: float | None = None) -> None:
        super().__init__()
        self.n_agents = check_int("n_agents", n_agents)
        self.state_dim = _optional_int("state_dim", state_dim)
        b = check_bounds(bounds)
        self.bounds = tuple(tuple(float(v) for v in row) for row in b)
        n = (n_per_axis, n_per_axis) if isinstance(n_per_axis, int | np.integer) \
            else tuple(n_per_axis)
        if len(n) != 2:
            raise ValueError(f"n_per_axis must be an int or (nx, ny), got {n_per_axis!r}.")
        self.nx, self.ny = (check_int("n_per_axis", v) for v in n)
        self.proximity_radius = check_positive("proximity_radius", proximity_radius)
        if isinstance(position_columns, slice):  # e.g. slice(0, 2) from Python code
            position_columns = range(position_columns.start or 0, position_columns.stop,
                                     position_columns.step or 1)
        self.position_columns = check_position_columns(position_columns, self.state_dim)
        self.max_value = float(self.n_agents)
        self.names = [f"cell({ix},{iy})" for iy in range(self.ny) for ix in range(self.nx)] \
            + ["proximity"]
        self._truth = (obstacle_centre, obstacle_radius, min_distance)
        lo = torch.tensor(b[:, 0])
        size = torch.tensor((b[:, 1] - b[:, 0]) / (self.nx, self.ny))
        self.register_buffer("_lo", lo, persistent=False)
        self.register_buffer("_cell_size", size, persistent=False)
        self.register_buffer("_columns", torch.tensor(self.position_columns), persistent=False)

    def cell_rectangles(self) -> np.ndarray:
        """``[nx ny, 4]`` float64 ``(x0, y0, x1, y1)`` of each cell, in feature order."""
        (x_lo, x_hi), (y_lo, y_hi) = self.bounds
        xs, ys = np.linspace(x_lo, x_hi, self.nx + 1), np.linspace(y_lo, y_hi, self.ny + 1)
        iy, ix = np.divmod(np.arange(self.nx * self.ny), self.nx)
        return np.stack([xs[ix], ys[iy], xs[ix + 1], ys[iy + 1]], -1)

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        if max(self.position_columns) >= states.shape[-1]:
            raise ValueError(f"{self.label}: position_columns {self.position_columns} do not "
                             f"fit states with d_s={states.shape[-1]} components; set "
                             f"position_columns to the columns of x and y.")
        pos = states.index_select(-1, self._columns)  # [..., N, 2]
        lo, size = self._lo.to(states.dtype), self._cell_size.to(states.dtype)
        ij = torch.floor((pos - lo) / size).long()
        ix, iy = ij[..., 0].clamp(0, self.nx - 1), ij[..., 1].clamp(0, self.ny - 1)
        cell = iy * self.nx + ix  # [..., N]
        counts = torch.zeros((*states.shape[:-2], self.nx * self.ny), dtype=states.dtype,
                             device=states.device)
        counts.scatter_add_(-1, cell, torch.ones_like(cell, dtype=states.dtype))
        diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)  # [..., N, N, 2]
        close = (diff * diff).sum(-1) < self.proximity_radius**2
        n = states.shape[-2]
        pairs = torch.triu(torch.ones(n, n, dtype=torch.bool, device=states.device), 1)
        prox = (close & pairs).flatten(-2).any(-1, keepdim=True).to(states.dtype)
        return torch.cat([counts, prox], -1)

    def true_constraints(self, disc_centre: Any = None, disc_radius: Any = None,
                         min_distance: float | None = None) -> torch.Tensor:
        """``[l]`` bool: the cells that overlap an obstacle disc, and the proximity
        feature when the agents must keep ``min_distance > 0`` apart.

        A cell overlaps a disc when the point of the cell's rectangle nearest to the
        centre is strictly closer than the radius (a cell only touching the disc's rim
        is free). Arguments left None take the constructor's ``obstacle_centre``,
        ``obstacle_radius`` and ``min_distance``.

        Args:
            disc_centre: ``[2]`` or ``[K, 2]`` obstacle centres.
            disc_radius: one radius or ``[K]``.
            min_distance: the least allowed distance between two agents (0 or None:
                none); it must equal ``proximity_radius``, the distance at which the
                proximity feature fires, or the feature would not mark exactly the
                violations.

        Raises:
            ValueError: no ground truth given, or inconsistent shapes / distances.
        """
        centre = self._truth[0] if disc_centre is None else disc_centre
        radius = self._truth[1] if disc_radius is None else disc_radius
        min_distance = self._truth[2] if min_distance is None else min_distance
        if centre is None or radius is None:
            raise ValueError(f"{self.label} has no ground truth: pass disc_centre and "
                             f"disc_radius (or build it with obstacle_centre= and "
                             f"obstacle_radius=).")
        c = np.asarray(centre, dtype=np.float64)
        if c.ndim not in (1, 2) or c.shape[-1] != 2 or not np.isfinite(c).all():
            raise ValueError(f"disc_centre must be [2] or [K, 2] finite coordinates, got "
                             f"{centre!r}.")
        c = c.reshape(-1, 2)
        r = np.asarray(radius, dtype=np.float64).reshape(-1)
        r = np.repeat(r, len(c)) if r.size == 1 else r
        if r.shape != (len(c),) or not (np.isfinite(r) & (r >= 0)).all():
            raise ValueError(f"disc_radius must be one non-negative number or one per disc "
                             f"({len(c)}), got {radius!r}.")
        rect = self.cell_rectangles()  # [C, 4]
        near = np.clip(c[None, :, :], rect[:, None, :2], rect[:, None, 2:])  # [C, K, 2]
        cells = (np.linalg.norm(near - c[None], axis=-1) < r[None]).any(1)
        prox = min_distance is not None and float(min_distance) > 0
        if prox and not np.isclose(float(min_distance), self.proximity_radius):
            raise ValueError(
                f"{self.label}: min_distance={min_distance} but the proximity feature fires "
                f"below proximity_radius={self.proximity_radius}; build the basis with "
                f"proximity_radius={min_distance} so the feature marks exactly the "
                f"violations.")
        return torch.from_numpy(np.append(cells, prox))

    def true_weights(self) -> torch.Tensor:
        """Ground-truth ``ω_cE`` in ``[0, 1]^l``: 1 on the true constraints (the
        constructor's ground truth)."""
        return self.true_constraints().to(torch.float64)
