"""What the grid world and the drone arena share as PettingZoo parallel envs: the
checks on calls and on the action dict, so that both refuse the same mistakes with the
same messages, and the plumbing around them (cached spaces, seeding, the step of a
finished episode, rendering off, closing). Each env checks the values of its own
actions. Both draw their pictures on a private Agg canvas (:func:`agg_axes`,
:func:`axes_image`)."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from gymnasium import logger, spaces
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from pettingzoo import ParallelEnv


class CheckedParallelEnv(ParallelEnv):
    """A :class:`ParallelEnv` whose subclasses set ``possible_agents``, ``agents`` and
    ``_index`` (agent name → index), report through :attr:`started` whether ``reset()``
    has been called, and implement :meth:`_observation_space`, :meth:`_action_space`,
    :meth:`_reset`, :meth:`_step` and :meth:`_render`."""

    metadata: dict[str, Any]
    possible_agents: list[str]
    agents: list[str]
    _index: dict[str, int]
    render_mode: str | None
    _rng: np.random.Generator | None

    @property
    def started(self) -> bool:
        """Whether ``reset()`` has been called."""
        raise NotImplementedError

    # ---- spaces -------------------------------------------------------------------
    # PettingZoo requires the same space object on every call (so seeding it sticks)
    # and recommends lru_cache (functools.cache is lru_cache(maxsize=None)); the few
    # small envs the cache keeps alive do not matter.
    @functools.cache  # noqa: B019
    def observation_space(self, agent: str) -> spaces.Space:
        self._agent_index(agent)
        return self._observation_space()

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        self._agent_index(agent)
        return self._action_space()

    def _observation_space(self) -> spaces.Space:  # pragma: no cover - abstract
        """Every agent's observation space (built once per agent)."""
        raise NotImplementedError

    def _action_space(self) -> spaces.Space:  # pragma: no cover - abstract
        """Every agent's action space (built once per agent)."""
        raise NotImplementedError

    # ---- episode ------------------------------------------------------------------
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode: every agent's observation and info. Like gymnasium, the
        env's random stream is reseeded only when ``seed`` is given (or at the first
        reset), so successive episodes differ; ``options`` go to :meth:`_reset`."""
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        return self._reset(options)

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """The reset of the episode's state, after the seeding (the stream is ``_rng``)."""
        raise NotImplementedError  # pragma: no cover - abstract

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Advance one step. ``actions`` must hold an action for every agent in
        ``agents``; actions of agents that are already done are ignored, and stepping a
        finished episode is a no-op (PettingZoo) that returns five empty dicts. Refuses
        a step before ``reset()``, a live agent without an action and an unknown agent;
        the env checks the values (:meth:`_step`)."""
        self._require_started("step")
        if not self.agents:
            return {}, {}, {}, {}, {}
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"No action given for active agent(s) {missing}; give one each.")
        for agent in actions:
            self._agent_index(agent)
        return self._step({agent: actions[agent] for agent in self.agents})

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of the live agents, ``given`` their unchecked actions in the order of
        ``agents``."""
        raise NotImplementedError  # pragma: no cover - abstract

    # ---- rendering ----------------------------------------------------------------
    def _check_render_mode(self, render_mode: str | None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, "
                f"got {render_mode!r}."
            )

    def render(self) -> np.ndarray | None:
        """The current frame as an ``H x W x 3`` uint8 image (``render_mode="rgb_array"``);
        None, with a warning, when the env was made without a render mode."""
        if self.render_mode is None:
            logger.warn("render() called with render_mode=None; pass render_mode='rgb_array'.")
            return None
        return self._render()

    def _render(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        pass

    # ---- checks -------------------------------------------------------------------
    def _require_started(self, method: str) -> None:
        if not self.started:
            raise RuntimeError(f"{method}() called before reset(); call env.reset(seed=...) "
                               "first.")

    def _agent_index(self, agent: str) -> int:
        try:
            return self._index[agent]
        except (KeyError, TypeError):  # TypeError: an unhashable "name"
            raise ValueError(
                f"Unknown agent {agent!r}; this env's agents are {self.possible_agents}."
            ) from None


def agg_axes(figsize: tuple[float, float]) -> Axes:
    """The axes of a new 80-dpi figure on its own Agg canvas: never pyplot's global
    state, so drawing is safe in headless and threaded code."""
    fig = Figure(figsize=figsize, dpi=80)
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def axes_image(ax: Axes, title: str) -> np.ndarray:
    """Finish a picture drawn on :func:`agg_axes`: equal aspect, the title (if any) and a
    tight layout; the figure as an ``H x W x 3`` uint8 image."""
    ax.set_aspect("equal")
    if title:
        ax.set_title(title, fontsize=8)
    fig = ax.figure
    fig.tight_layout()
    return figure_image(fig)


def figure_image(fig: Figure) -> np.ndarray:
    """A figure on its own Agg canvas (:func:`agg_axes`), drawn, as an ``H x W x 3``
    uint8 image (for pictures laid out by hand, without :func:`axes_image`'s tight
    layout)."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
