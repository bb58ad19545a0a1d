"""What the grid world and the drone arena share as PettingZoo parallel envs: the
checks on calls and on the action dict, so that both refuse the same mistakes with the
same messages. Each env checks the values of its own actions."""

from __future__ import annotations

from typing import Any

from pettingzoo import ParallelEnv


class CheckedParallelEnv(ParallelEnv):
    """A :class:`ParallelEnv` whose subclasses set ``possible_agents``, ``agents`` and
    ``_index`` (agent name → index) and report through :attr:`started` whether
    ``reset()`` has been called."""

    possible_agents: list[str]
    agents: list[str]
    _index: dict[str, int]

    @property
    def started(self) -> bool:
        """Whether ``reset()`` has been called."""
        raise NotImplementedError

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

    def _live_actions(self, actions: dict[str, Any]) -> dict[str, Any] | None:
        """The actions of the agents still in ``agents``, unchecked values, in the order
        of ``agents``; ``None`` when the episode is over (PettingZoo: stepping a finished
        episode is a no-op). Refuses a step before ``reset()``, a live agent without an
        action and an unknown agent; actions of agents already done are ignored."""
        self._require_started("step")
        if not self.agents:
            return None
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"No action given for active agent(s) {missing}; give one each.")
        for agent in actions:
            self._agent_index(agent)
        return {agent: actions[agent] for agent in self.agents}
