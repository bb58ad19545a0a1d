"""A constrained version of Farama's MPE ``simple_spread`` (package ``mpe2``), as a
PettingZoo ``ParallelEnv``: the first third-party game D-ICRL runs on.

Geometry (mpe2's units, ``x`` to the right, ``y`` up; defaults for 2 agents)::

      y
     1.5 ┌──────────────────────────────────────────────────────┐  walls at ±1.5
         │                                                      │
     0.5 │  ┌─────┐                                             │
         │  │start│            ╭─────╮    x L0          x L1  │
       0 │  │region            │  d  │                          │  d: centre (0, 0), r 0.3
         │  │     │            ╰─────╯                          │  L0 = (0.5625, 0.1875)
    -0.5 │  └─────┘                                             │  L1 = (1.3125, 0.1875)
    -1.5 └──────────────────────────────────────────────────────┘
          -1.2  -0.8              0         0.5        1.0    1.5

The agents start anywhere in the start region (uniformly, at least
``min_distance + START_MARGIN`` apart) and must cover the landmarks, which lie in a
row behind the forbidden disc (3 agents, staggered: ``(0.5625, 0.1875), (0.9375, -0.1875),
(1.3125, 0.1875)``). Each default landmark is the centre of a cell of the 8 × 8 cost grid
(``features/cost=position_cells``). With landmarks on cell boundaries (the row
``(0.5, 0), (1.0, 0)`` of earlier versions), experts rest on one side of a boundary and
any policy resting a hair across it accrues a cell they never visit, which the learners
then forbid (docs/mpe.md). Every
straight route from a start to a landmark crosses the disc, and the straight routes
converge on the row, so an unconstrained team violates both kinds of true constraints
(:class:`~dicrl_torch.demos.mpe_experts.NominalController`: in nearly every episode of
the nominal game, see the tests):

- an agent inside the **forbidden disc** (distance to its centre below its radius);
- two active agents closer than **``min_distance``** (both violate).

In the true game (``constrained=True``) a violator freezes, as in the drone arena
(:mod:`dicrl_torch.envs.drones`): it stops where it is, its actions are ignored, it is
terminated and leaves ``agents``, and it no longer collides or counts for the distance
constraint (it stays in :meth:`ConstrainedSpread.state` and in the other agents'
observations, where it stopped). In the nominal game violations are only reported.

**Task success** (:meth:`ConstrainedSpread.task_success`): at the end of the episode
every landmark lies within :data:`SUCCESS_RADIUS` (0.1, mpe2's own capture radius of
``simple_spread``) of a distinct agent, and no agent violated a constraint during the
episode. The covering test alone is :func:`landmarks_covered`.

The package holds the game in three concerns, and a fourth for speed:
:mod:`~dicrl_torch.envs.mpe.layout` (the geometry, the start sampler, the constraint and
covering tests, the matching of agents to landmarks), :mod:`~dicrl_torch.envs.mpe.env`
(:class:`ConstrainedSpread` on mpe2's world), :mod:`~dicrl_torch.envs.mpe.render` (the
picture) and, for the SAC solver's collection, :mod:`~dicrl_torch.envs.mpe.vector`
(:class:`SpreadVectorEnv`, many episodes of its joint env stepped as one array
computation). The experts that fly it,
:class:`~dicrl_torch.demos.mpe_experts.NominalController` (every agent straight to its
landmark, ignoring the constraints; it violates both kinds) and
:class:`~dicrl_torch.demos.mpe_experts.ViaPointController` (around the disc in lanes,
with start delays planned so that the agents keep apart; succeeds without violation),
and :func:`~dicrl_torch.demos.mpe_experts.run_episode`, are demonstration generation and
live with the demonstrations, in :mod:`dicrl_torch.demos.mpe_experts`.
"""

from __future__ import annotations

from dicrl_torch.envs.mpe import layout
from dicrl_torch.envs.mpe.env import ConstrainedSpread

# The geometry, start sampler and tests: layout's whole public API, named once, by its
# __all__.
from dicrl_torch.envs.mpe.layout import *  # noqa: F403
from dicrl_torch.envs.mpe.render import render_spread
from dicrl_torch.envs.mpe.vector import SpreadVectorEnv

__all__ = ["ConstrainedSpread", "SpreadVectorEnv", "render_spread"]
__all__ += layout.__all__
