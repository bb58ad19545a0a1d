"""The planning pieces (dicrl_torch/solvers/planning.py) against independent truth."""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest

from dicrl_torch.solvers.planning import FORBIDDEN_VALUE, CrossEntropyPlanner, grid_values

GAMMA = 0.95


def travel_times(forbidden: np.ndarray, goal: np.ndarray, steps_per_cell: float) -> np.ndarray:
    """Dijkstra over the 8-connected free centres: the least time (steps) to a goal."""
    G = forbidden.shape[0]
    time = np.full(forbidden.shape, np.inf)
    heap = [(0.0, i, j) for i, j in zip(*np.nonzero(goal), strict=True)]
    for _, i, j in heap:
        time[i, j] = 0.0
    while heap:
        t, i, j = heapq.heappop(heap)
        if t > time[i, j]:
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                a, b = i + di, j + dj
                if (di, dj) == (0, 0) or not (0 <= a < G and 0 <= b < G) or forbidden[a, b]:
                    continue
                u = t + steps_per_cell * math.hypot(di, dj)
                if u < time[a, b]:
                    time[a, b] = u
                    heapq.heappush(heap, (u, a, b))
    return time


def test_grid_values_are_the_discounted_travel_times_round_forbidden_centres():
    """Reward 1 at the goal only: V = γ^T / (1 - γ) with T the shortest flight time round
    the forbidden centres (Dijkstra); enclosed centres stay (0); forbidden ones are
    FORBIDDEN_VALUE."""
    G = 9
    forbidden = np.zeros((G, G), bool)
    forbidden[4, 1:8] = True  # a wall across the middle, open at both ends
    forbidden[0:3, 6] = forbidden[2, 6:9] = True  # a sealed corner pocket
    goal = np.zeros((G, G), bool)
    goal[8, 4] = True
    values = grid_values(goal.astype(float), forbidden, goal, steps_per_cell=1.5,
                         gamma=GAMMA)
    time = travel_times(forbidden, goal, 1.5)
    free = ~forbidden
    expect = np.where(np.isfinite(time), GAMMA ** np.where(np.isfinite(time), time, 0)
                      / (1 - GAMMA), 0.0)
    np.testing.assert_allclose(values[free], expect[free], rtol=1e-6)
    assert (values[forbidden] == FORBIDDEN_VALUE).all()
    assert values[0, 8] == 0.0 and np.isinf(time[0, 8])  # in the pocket: no way out
    # Round the wall: a centre just below it is farther (in time) than its distance.
    assert time[3, 4] > 5 * 1.5


def test_grid_values_stay_where_staying_pays_and_refuse_bad_input():
    G = 5
    reward = np.full((G, G), 2.0)
    reward[0, 0] = 3.0
    none = np.zeros((G, G), bool)
    values = grid_values(reward, none, none, steps_per_cell=1.0, gamma=GAMMA)
    assert values[0, 0] == pytest.approx(3.0 / (1 - GAMMA))
    # Elsewhere: fly to (0, 0), earning 2 on the way, better than staying at 2.
    assert (values[1:, 1:] > 2.0 / (1 - GAMMA)).all()
    with pytest.raises(ValueError, match="square"):
        grid_values(np.zeros((2, 3)), np.zeros((2, 3), bool), np.zeros((2, 3), bool),
                    steps_per_cell=1.0, gamma=GAMMA)
    with pytest.raises(ValueError, match="NaN"):
        grid_values(np.full((2, 2), np.nan), np.zeros((2, 2), bool), np.zeros((2, 2), bool),
                    steps_per_cell=1.0, gamma=GAMMA)
    with pytest.raises(ValueError, match="gamma"):
        grid_values(reward, none, none, steps_per_cell=1.0, gamma=1.0)


def _point_planner(seed=0, replan=1) -> CrossEntropyPlanner:
    """One point agent, ``x' = x + 0.2 a``, goal disc at (2, 0), a wall x in [0.9, 1.1],
    |y| < 1 between; the reward is 1 at the goal (absorbing), the terminal value the
    negative distance to the goal. ``seed``: an int (one problem) or one seed per problem."""
    goal = np.array([2.0, 0.0])

    def step(states, active, actions):
        moved = states + 0.2 * np.clip(actions, -1, 1) * active[..., None]
        arrived = np.linalg.norm(moved[..., 0, :] - goal, axis=-1) < 0.3
        return moved, active & ~arrived[..., None]

    def reward(states):
        return (np.linalg.norm(states[..., 0, :] - goal, axis=-1) < 0.3).astype(float)

    def wall(states):
        x, y = states[..., 0, 0], states[..., 0, 1]
        return (np.abs(x - 1.0) < 0.1) & (np.abs(y) < 1.0)

    def terminal(states):
        return -np.linalg.norm(states[:, 0, :] - goal, axis=-1)

    return CrossEntropyPlanner(step_fn=step, reward_fn=reward, forbidden_fn=wall,
                               terminal_fn=terminal, action_shape=(1, 2), gamma=GAMMA,
                               horizon=20, knot=4, replan=replan, samples=128, iterations=4,
                               elites=12, seed=seed)


def _fly(planner, starts, steps, which=None):
    """Fly problems ``which`` (default all) from ``starts [P, 1, 2]`` for up to ``steps``
    steps, each stopping at the goal; ``(paths [P] of [t, 1, 2], actions [P] of lists)``."""
    which = np.arange(planner.problems) if which is None else np.asarray(which)
    state, active = starts.copy(), np.ones((len(which), 1), bool)
    paths = [[s.copy()] for s in state]
    actions = [[] for _ in which]
    for _ in range(steps):
        flying = np.flatnonzero(active.any(-1))
        if not len(flying):
            break
        a = planner.act(state[flying], active[flying], which[flying])
        moved, still = planner.step_fn(state[flying], active[flying], a)
        for j, k in enumerate(flying):
            actions[k].append(a[j])
            paths[k].append(moved[j].copy())
        state[flying], active[flying] = moved, still
    return [np.stack(p) for p in paths], actions


def test_cross_entropy_planner_flies_round_a_wall_to_the_goal():
    planner = _point_planner()
    paths, actions = _fly(planner, np.zeros((1, 1, 2)), 60)
    path = paths[0]
    assert np.linalg.norm(path[-1, 0] - [2.0, 0.0]) < 0.3, "the goal was not reached in 60 steps"
    assert not planner.forbidden_fn(path[:, None]).any()
    assert np.abs(path[:, 0, 1]).max() >= 1.0  # it went round the wall's end
    # The same seed plans the same actions.
    twin = _point_planner()
    state, active = np.zeros((1, 1, 2)), np.ones((1, 1), bool)
    for a in actions[0][:5]:
        np.testing.assert_array_equal(twin.act(state, active)[0], a)
        state, active = twin.step_fn(state, active, a[None])


def test_cross_entropy_planner_batches_independent_problems():
    """Problems planned together (one model call on all their plans, episodes ending at
    different steps) fly exactly as each planned alone with its seed, and a subset asked
    for by ``which`` as well."""
    starts = np.array([[[0.0, 0.0]], [[0.0, 0.5]], [[1.5, -1.5]]])
    together, acts = _fly(_point_planner(seed=[3, 4, 5]), starts, 60)
    assert len({len(p) for p in together}) > 1  # the episodes end at different steps
    for k, seed in enumerate([3, 4, 5]):
        alone, alone_acts = _fly(_point_planner(seed=seed), starts[k:k + 1], 60)
        np.testing.assert_array_equal(alone[0], together[k])
        np.testing.assert_array_equal(np.stack(alone_acts[0]), np.stack(acts[k]))
    subset, _ = _fly(_point_planner(seed=[3, 4, 5]), starts[[2, 0]], 60, which=[2, 0])
    np.testing.assert_array_equal(subset[0], together[2])
    np.testing.assert_array_equal(subset[1], together[0])
    planner = _point_planner(seed=[3, 4])
    with pytest.raises(ValueError, match="distinct problems"):
        planner.act(np.zeros((2, 1, 2)), np.ones((2, 1), bool), [1, 1])
    with pytest.raises(ValueError, match="one row per problem"):
        planner.act(np.zeros((1, 1, 2)), np.ones((1, 1), bool), [0, 1])


def test_replanning_once_per_knot_flies_each_plan_open_loop_between():
    """replan=knot: a round of plans only where a knot starts, the planned action held
    for the knot in between. Checked against the per-step planner itself: a planner that
    re-plans every step, asked only at those steps (its plan shifted by hand as the held
    steps pass), chooses the same actions; and the rollouts are knot times fewer."""
    calls = []

    def counted(planner):
        step = planner.step_fn
        planner.step_fn = lambda *a: (calls.append(len(a[0])), step(*a))[1]
        return planner

    sparse = counted(_point_planner(seed=7, replan=4))
    start = np.zeros((1, 1, 2))
    paths, actions = _fly(sparse, start, 60)
    assert np.linalg.norm(paths[0][-1, 0] - [2.0, 0.0]) < 0.3, "the goal was not reached"
    assert not sparse.forbidden_fn(paths[0][:, None]).any()
    acts = np.stack(actions[0])
    steps = len(acts)
    for k in range(0, steps, 4):  # each knot's action is held for its 4 steps
        held = acts[k:k + 4]
        np.testing.assert_array_equal(held, np.repeat(held[:1], len(held), 0))
    # The dense planner from the same seed, planning only at the knots' first steps.
    dense = _point_planner(seed=7)
    state, active = start.copy(), np.ones((1, 1), bool)
    for t in range(steps):
        if t % 4 == 0:
            np.testing.assert_array_equal(dense.act(state, active)[0], acts[t])
            dense._held[:] = 0  # the held steps pass without it: shift as act would have
            dense._plan = np.concatenate([dense._plan[:, 1:], dense._plan[:, -1:]], axis=1)
        state, active = dense.step_fn(state, active, acts[t][None])
    # Rollouts: one step_fn call per planned step per round per knot; the flight's own
    # steps are _fly's calls (one per step).
    plan_calls = sum(1 for c in calls if c > 1)
    assert plan_calls == -(-steps // 4) * 4 * 20
    with pytest.raises(ValueError, match="replan=3 is invalid.*dividing knot=4"):
        _point_planner(replan=3)


def _posts_planner(seed: int, n: int = 2) -> CrossEntropyPlanner:
    """``n`` points side by side, point ``i`` at ``(2 i, 0)`` in the corridor
    ``|x - 2 i| <= 0.6`` with a post ``|x - 2 i| < 0.3, y in (0.4, 0.8)`` above it; one
    joint plan, rewarded by the points' heights."""
    offsets = 2.0 * np.arange(n)

    def step(states, active, actions):
        return states + 0.2 * np.clip(actions, -1, 1) * active[..., None], active

    def blocked(states):
        x, y = states[..., 0] - offsets, states[..., 1]
        return ((np.abs(x) > 0.6) | ((np.abs(x) < 0.3) & (y > 0.4) & (y < 0.8))).any(-1)

    return CrossEntropyPlanner(
        step_fn=step, reward_fn=lambda states: states[..., 1].sum(-1), forbidden_fn=blocked,
        terminal_fn=lambda states: 10 * states[:, :, 1].sum(-1), action_shape=(n, 2),
        gamma=GAMMA, horizon=20, knot=4, samples=128, iterations=4, elites=12, seed=seed)


def test_the_planner_flies_the_best_plan_it_scored():
    """The action is the first knot of the highest-return plan among every plan scored
    in the call's rounds (read from the planner's own scoring)."""
    planner = _posts_planner(seed=0)
    scored = []
    score = planner.returns
    planner.returns = lambda *a: (scored.append((a[2], score(*a))), scored[-1][1])[1]
    state, active = np.zeros((1, 2, 2)), np.ones((1, 2), bool)
    state[0, 1, 0] = 2.0
    for _ in range(6):
        scored.clear()
        action = planner.act(state, active)
        knots = np.concatenate([k[0] for k, _ in scored])  # [rounds * S, K, 2, 2]
        returns = np.concatenate([r[0] for _, r in scored])
        np.testing.assert_array_equal(action[0], knots[np.argmax(returns), 0])
        state, active = planner.step_fn(state, active, action)


def test_two_points_pass_their_posts_where_the_elites_mean_runs_into_them():
    """Each point must pass its post on one side; the elites mix both sides per point,
    so their mean heads into the posts (flown, it entered or stalled below them at
    every one of these seeds)."""
    for seed in range(10):
        planner = _posts_planner(seed)
        state, active = np.array([[[0.0, 0.0], [2.0, 0.0]]]), np.ones((1, 2), bool)
        for _ in range(40):
            state, active = planner.step_fn(state, active, planner.act(state, active))
            assert not planner.forbidden_fn(state[None])[0, 0], f"seed {seed} entered"
        assert state[0, :, 1].min() > 0.8, f"seed {seed}: stuck below a post"


def test_cross_entropy_planner_refuses_bad_sizes():
    kwargs = dict(step_fn=None, reward_fn=None, forbidden_fn=None, terminal_fn=None,
                  action_shape=(1, 2), gamma=GAMMA)
    with pytest.raises(ValueError, match="multiple of knot"):
        CrossEntropyPlanner(**kwargs, horizon=10, knot=3)
    with pytest.raises(ValueError, match="elites=50 is invalid.*at most samples=20"):
        CrossEntropyPlanner(**kwargs, samples=20, elites=50)
    with pytest.raises(ValueError, match="samples=0 is invalid: it must be an int >= 1"):
        CrossEntropyPlanner(**kwargs, samples=0)


@pytest.mark.parametrize("per_agent", [True, False])
def test_the_drones_grid_values_forbid_a_learned_unit_for_every_drone_it_binds(per_agent):
    """A learned local unit is a wall in the terminal values of each drone it binds: its
    owner's, or every drone's when the drones share the unit (it counts the drones in
    it). Without it the planner aimed through a learned region it must not enter and
    hovered at its edge. A learned separation ring binds no drone alone."""
    from dicrl_torch.envs.drones import DroneDynamics
    from dicrl_torch.features.drone import DoorLocationRewardBasis
    from dicrl_torch.features.local import LocalReLUBasis
    from dicrl_torch.solvers.drone_planning import drone_grid_values

    cost = LocalReLUBasis(n_agents=2, bounds=[[0, 10], [0, 10]], n_centres=40, n_rings=6,
                          per_agent=per_agent, agent_prefix="drone", seed=0, state_dim=4)
    reward = DoorLocationRewardBasis()
    unit = int(np.argmin(np.linalg.norm(cost.centres.numpy() - 5.0, axis=1)))  # mid-room
    learned = np.zeros(cost.dim, dtype=bool)
    learned[unit] = True  # drone 0's unit, or the shared one
    learned[-1] = True  # the widest separation ring: no wall for a drone alone
    eta = np.array([1.0] * reward.dim + [-10.0])
    values = drone_grid_values(reward, cost, eta, learned.astype(float), learned, n_agents=2,
                               margin=0.1, grid_step=0.25, dynamics=DroneDynamics(),
                               gamma=0.99)
    centre = np.clip((cost.centres.numpy()[unit] / 0.25).astype(int), 0, 39)
    walled = [bool(v[centre[1], centre[0]] == FORBIDDEN_VALUE) for v in values]
    assert walled == ([True, False] if per_agent else [True, True])
    assert all((v == FORBIDDEN_VALUE).sum() < 0.25 * 40 * 40 for v in values)  # not the ring
