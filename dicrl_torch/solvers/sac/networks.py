"""SAC's networks for an ensemble of learners: each layer one batched matrix product.

A learner's actor is a squashed-Gaussian MLP and its critic a twin of MLPs, as SB3's
``MlpPolicy`` for SAC builds them (same layers, activations, initial distribution,
``log_std`` clamp). Here every weight carries a leading ensemble axis: ``E`` learners
(the learners a process trains together, or one) stacked, and for the critics each
learner's two critics beside each other (``2 E``), so that a layer of all of them is one
``baddbmm`` and their optimiser one fused call. A 64-unit network's layer is a few
microseconds of arithmetic; what the stacking removes is the per-call overhead that
dominated SB3's update (docs/performance.md, "The SAC solver").

Slices of the ensemble axis never mix: the loss of ``E`` learners is the sum of each
learner's own, so each learner's gradients, Adam moments and target networks are what
they would be alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["EnsembleActor", "EnsembleCritic", "LOG_STD_MAX", "LOG_STD_MIN",
           "squashed_sample"]

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # SB3's SAC actor clamps its log-std to these
_SQUASH_EPSILON = 1e-6  # SB3's SquashedDiagGaussianDistribution epsilon
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def _init_layers(dims: Sequence[int], copies: int,
                 generators: Sequence[torch.Generator]) -> list[torch.Tensor]:
    """``[W_1, b_1, W_2, b_2, ...]``: ``W_k`` ``[E * copies, d_{k-1}, d_k]``, ``b_k``
    ``[E * copies, 1, d_k]``, each learner's drawn from its own generator (torch's
    ``nn.Linear`` default: uniform in ``±1/sqrt(fan_in)``, weights and biases), so a
    learner's initial networks do not depend on the others in its ensemble."""
    per_learner = []
    for gen in generators:
        layers = []
        for _ in range(copies):
            for d_in, d_out in zip(dims[:-1], dims[1:], strict=True):
                bound = 1.0 / math.sqrt(d_in)
                w = torch.empty(d_in, d_out).uniform_(-bound, bound, generator=gen)
                b = torch.empty(1, d_out).uniform_(-bound, bound, generator=gen)
                layers.append((w, b))
        per_learner.append(layers)
    n_layers = len(dims) - 1
    out = []
    for k in range(n_layers):
        ws = [layers[c * n_layers + k][0] for layers in per_learner for c in range(copies)]
        bs = [layers[c * n_layers + k][1] for layers in per_learner for c in range(copies)]
        out += [torch.stack(ws), torch.stack(bs)]
    return out


def mlp(x: torch.Tensor, params: Sequence[torch.Tensor]) -> torch.Tensor:
    """ReLU MLP of stacked layers: ``x`` ``[M, B, d_0]`` -> ``[M, B, d_L]`` (no activation
    after the last layer); ``params`` as :func:`_init_layers` gives them."""
    n = len(params) // 2
    for k in range(n):
        x = torch.baddbmm(params[2 * k + 1], x, params[2 * k])
        if k < n - 1:
            x = torch.relu(x)
    return x


class _Stacked(nn.Module):
    """Parameters ``layer{k}_weight`` / ``layer{k}_bias`` of an ensemble MLP."""

    def __init__(self, dims: Sequence[int], copies: int,
                 generators: Sequence[torch.Generator]) -> None:
        super().__init__()
        self.dims = tuple(int(d) for d in dims)
        self.n_learners = len(generators)
        params = _init_layers(self.dims, copies, generators)
        for k in range(len(self.dims) - 1):
            self.register_parameter(f"layer{k}_weight", nn.Parameter(params[2 * k]))
            self.register_parameter(f"layer{k}_bias", nn.Parameter(params[2 * k + 1]))
        self.params = list(self.parameters())

    def learner_state(self, e: int) -> dict[str, torch.Tensor]:
        """Learner ``e``'s slice of every parameter (copies of it)."""
        copies = self.params[0].shape[0] // self.n_learners
        return {name: p.detach()[e * copies:(e + 1) * copies].clone()
                for name, p in self.named_parameters()}

    def load_learner_state(self, e: int, state: dict[str, torch.Tensor]) -> None:
        """Set learner ``e``'s slice from a :meth:`learner_state`."""
        copies = self.params[0].shape[0] // self.n_learners
        with torch.no_grad():
            for name, p in self.named_parameters():
                p[e * copies:(e + 1) * copies].copy_(state[name])


class EnsembleActor(_Stacked):
    """``E`` squashed-Gaussian actors ``obs [E, B, d_o] -> mean, log_std [E, B, d_a]``.

    Args:
        obs_dim, action_dim: ``d_o`` and ``d_a``.
        hidden: hidden layer widths (e.g. ``(64, 64)``).
        generators: one per learner, for its initial weights.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int],
                 generators: Sequence[torch.Generator]) -> None:
        # One head of 2 d_a outputs: the mean's and the log-std's (SB3's two heads).
        super().__init__([obs_dim, *hidden, 2 * action_dim], 1, generators)
        self.action_dim = int(action_dim)

    def dist_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and clamped log-std ``[E, B, d_a]`` (pre-squash) at ``obs`` ``[E, B, d_o]``."""
        out = mlp(obs, self.params)
        return out[..., :self.action_dim], out[..., self.action_dim:].clamp(LOG_STD_MIN,
                                                                             LOG_STD_MAX)


def squashed_sample(mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Actions ``tanh(mean + noise std)`` and their log-densities ``[..., 1]`` (SB3's
    squashed diagonal Gaussian with its epsilon), ``noise`` standard normal of
    ``mean``'s shape ``[..., d_a]``."""
    action = torch.tanh(mean + noise * log_std.exp())
    log_prob = (-0.5 * noise * noise - log_std - _HALF_LOG_2PI
                - torch.log(1 - action * action + _SQUASH_EPSILON)).sum(-1, keepdim=True)
    return action, log_prob


class EnsembleCritic(_Stacked):
    """``E`` twin critics ``(obs [E, B, d_o], actions [E, B, d_a]) -> [E, 2, B, G]``:
    each learner's two soft-Q networks of ``G`` reward columns.

    Args:
        obs_dim, action_dim: ``d_o`` and ``d_a``.
        hidden: hidden layer widths.
        n_rewards: ``G``, the reward columns (1: the joint soft Q).
        generators: one per learner.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int], n_rewards: int,
                 generators: Sequence[torch.Generator]) -> None:
        super().__init__([obs_dim + action_dim, *hidden, n_rewards], 2, generators)

    def forward_with(self, params: Sequence[torch.Tensor], obs: torch.Tensor,
                     actions: torch.Tensor) -> torch.Tensor:
        """The critics of ``params`` (this module's or a target copy's) at
        ``(obs, actions)``: ``[E, 2, B, G]``."""
        x = torch.cat([obs, actions], -1)  # [E, B, d]
        e, b, d = x.shape
        x = x.unsqueeze(1).expand(e, 2, b, d).reshape(2 * e, b, d)
        return mlp(x, params).reshape(e, 2, b, -1)
