"""Tests of the drone arena, its demonstrations and feature bases (docs/design.md §7)."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from npz_files import assert_file_refused, assert_not_an_archive
from pettingzoo.test import parallel_api_test, parallel_seed_test

from dicrl_torch.demos import Trajectories, partition_demonstrations
from dicrl_torch.demos.drone_demos import (
    PAPER_DRONE_SPLIT,
    DroneDemonstrations,
    load_drone_demonstrations,
    make_drone_demonstrations,
    path_clearance,
    replay_pair,
    save_drone_demonstrations,
)
from dicrl_torch.envs.drones import (
    AGENTS,
    CELL_SIZE,
    DOOR_DEPTH,
    DOORS,
    GRID_CELLS,
    NOMINAL_STARTS,
    OBSTACLES,
    PROXIMITY_RADIUS,
    ROOM_SIZE,
    START_JITTER,
    DroneArena,
    DroneDynamics,
    JointDroneEnv,
    in_obstacle,
    joint_obs_to_state,
    joint_step,
    nominal_step,
    obstacle_cell_mask,
    render_arena,
)
from dicrl_torch.features.drone import (
    CellOccupancyCostBasis,
    DoorLocationRewardBasis,
    FourierRewardBasis,
    RBFCostBasis,
)

torch.set_num_threads(1)
D0, D1 = AGENTS


def cell(ix: int, iy: int) -> int:
    return iy * GRID_CELLS + ix


def arena(positions, **kw) -> DroneArena:
    """An env reset with seed 0 and the given start positions."""
    env = DroneArena(**kw)
    env.reset(seed=0, options={"positions": positions})
    return env


def fly(env: DroneArena, commands: dict, steps: int) -> list[dict]:
    """Apply constant ``commands`` (to the agents still flying); return the infos."""
    out = []
    for _ in range(steps):
        if not env.agents:
            break
        out.append(env.step({a: np.asarray(commands.get(a, (0.0, 0.0)), dtype=np.float32)
                             for a in env.agents})[4])
    return out


# ---- PettingZoo / gymnasium API -----------------------------------------------------
@pytest.mark.parametrize("constrained", [True, False])
def test_parallel_api_and_seed(constrained):
    env = DroneArena(constrained=constrained, max_steps=150)
    with warnings.catch_warnings():  # the API test only warns on wrong dict keys
        warnings.simplefilter("error", UserWarning)
        parallel_api_test(env, num_cycles=200)
    parallel_seed_test(lambda: DroneArena(constrained=constrained))


def test_observations_stay_in_spaces():
    env = DroneArena(constrained=False, max_steps=200)
    obs, _ = env.reset(seed=3)
    for a in env.agents:
        env.action_space(a).seed(3)
    while env.agents:
        for a, o in obs.items():
            assert o.dtype == np.float32 and env.observation_space(a).contains(o), (a, o)
        assert env.state_space.contains(env.state())
        obs = env.step({a: env.action_space(a).sample() for a in env.agents})[0]


def test_joint_env_passes_checkers():
    check_env(JointDroneEnv(), skip_render_check=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "no spec" notes, not failures
        check_env(JointDroneEnv(render_mode="rgb_array"))
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    sb3_check_env(JointDroneEnv(), warn=True)


def test_joint_env_reward_termination_and_state():
    calls = []

    def reward_fn(obs, action, next_obs):
        calls.append((obs.shape, action.shape, next_obs.shape))
        return float(joint_obs_to_state(next_obs)[0, 1])  # drone 0's height

    env = JointDroneEnv(reward_fn=reward_fn, max_steps=400)
    obs, info = env.reset(seed=1, options={"positions": [[8.75, 8.5], [1.25, 8.5]]})
    np.testing.assert_allclose(joint_obs_to_state(obs), info["state"], atol=1e-6)
    np.testing.assert_allclose(joint_obs_to_state(torch.as_tensor(obs)).numpy(),
                               info["state"], atol=1e-6)
    done = False
    while not done:  # both fly straight up through their doors
        obs, r, term, trunc, info = env.step(np.array([0, 1, 0, 1], dtype=np.float32))
        assert r == pytest.approx(env.state()[0, 1], abs=1e-5)
        assert not trunc
        done = term
    assert info["reached"].any() and not env.arena.active.any()
    assert env.arena.reached.all() and not env.arena.violated.any()
    assert calls[0] == ((20,), (4,), (20,))
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4))
    env.reset(seed=1)
    with pytest.raises(ValueError, match=r"\[4\]"):
        env.step(np.zeros(3))


def test_joint_env_truncates_at_step_limit():
    env = JointDroneEnv(max_steps=5)
    env.reset(seed=0)
    flags = [env.step(np.zeros(4))[2:4] for _ in range(5)]
    assert flags[:-1] == [(False, False)] * 4 and flags[-1] == (False, True)


# ---- determinism and dynamics -------------------------------------------------------
def rollout(seed: int, steps: int = 40) -> np.ndarray:
    env = DroneArena(constrained=False)
    env.reset(seed=seed)
    for t in range(steps):
        env.step({D0: np.array([0.5, np.sin(t / 5)]), D1: np.array([-0.5, 0.3])})
    return env.trajectory()


def test_same_seed_same_trajectory():
    np.testing.assert_array_equal(rollout(7), rollout(7))
    assert not np.array_equal(rollout(7), rollout(8))
    starts = np.stack([_start(s) for s in range(20)])
    assert np.all(np.abs(starts - np.asarray(NOMINAL_STARTS)) <= START_JITTER)
    assert len({tuple(s.ravel()) for s in starts}) == 20  # the seed randomises the start


def _start(seed: int) -> np.ndarray:
    env = DroneArena()
    env.reset(seed=seed)
    return env.state()[:, :2]


def test_first_order_response_reaches_command():
    dyn = DroneDynamics(noise_std=0.0)
    pos, vel = np.full(2, 5.0), np.zeros(2)  # the middle of the room: no wall in reach
    u = np.array([0.6, -0.3])
    p1, v1 = dyn.step(pos, vel, u)
    np.testing.assert_allclose(v1, dyn.dt / dyn.tau * u * dyn.max_speed)
    np.testing.assert_allclose(p1, pos + dyn.dt * v1)
    for _ in range(40):  # 4 s = 13 time constants
        pos, vel = dyn.step(pos, vel, u)
    np.testing.assert_allclose(vel, u * dyn.max_speed, atol=1e-5)
    # Commands beyond the box are clipped to it.
    _, v = dyn.step(np.zeros(2), np.array([1.0, 0.0]), np.array([5.0, 0.0]))
    assert v[0] == pytest.approx(1.0)


def test_disc_commands_bound_the_speed_in_every_direction():
    """Under ``"box"`` the diagonal command flies sqrt 2 times faster than an axis
    command; under ``"disc"`` every direction tops out at ``max_speed``, and commands
    inside the unit disc fly as under the box."""
    def settle(dyn, u):
        pos, vel = np.full(2, 5.0), np.zeros(2)
        for _ in range(40):  # 13 time constants, the drone held in the middle (no wall)
            pos, vel = dyn.step(pos, vel, np.asarray(u, dtype=float))
            pos = np.full(2, 5.0)
        return vel

    box = DroneDynamics(noise_std=0.0, max_speed=1.5)
    disc = DroneDynamics(noise_std=0.0, max_speed=1.5, command_set="disc")
    assert np.linalg.norm(settle(box, [1, 1])) == pytest.approx(1.5 * np.sqrt(2), rel=1e-5)
    np.testing.assert_allclose(settle(disc, [1, 1]), [1.5 / np.sqrt(2)] * 2, rtol=1e-5)
    np.testing.assert_allclose(settle(disc, [-1, 0]), [-1.5, 0.0], atol=1e-5)
    np.testing.assert_allclose(settle(disc, [3, -4]), [1.5 * 0.6, -1.5 * 0.8], rtol=1e-5)
    np.testing.assert_allclose(settle(disc, [0.3, -0.2]), settle(box, [0.3, -0.2]))
    # bound() is the applied command, the same in numpy and torch.
    cmd = np.random.default_rng(0).uniform(-2, 2, size=(50, 2))
    bounded = disc.bound(cmd)
    assert (np.linalg.norm(bounded, axis=-1) <= 1 + 1e-12).all()
    np.testing.assert_allclose(disc.bound(torch.as_tensor(cmd)).numpy(), bounded)
    np.testing.assert_array_equal(box.bound(cmd), np.clip(cmd, -1, 1))
    with pytest.raises(ValueError, match="command_set must be one of"):
        DroneDynamics(command_set="circle")


def test_noise_is_seeded_and_scaled():
    def hover(seed):
        env = arena([[5.0, 2.0], [5.0, 8.9]], constrained=False, max_steps=2000)
        env.reset(seed=seed, options={"positions": [[5.0, 2.0], [5.0, 8.9]]})
        vels = []
        for _ in range(1500):
            env.step({a: np.zeros(2) for a in env.agents})
            vels.append(env.state()[:, 2:])
        return np.array(vels)

    a, b, c = hover(1), hover(1), hover(2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # Stationary std of v' = (1 - k) v + σ ε with k = dt/τ is σ / sqrt(1 - (1 - k)^2).
    dyn = DroneDynamics()
    k = dyn.dt / dyn.tau
    want = dyn.noise_std / np.sqrt(1 - (1 - k) ** 2)
    assert a[100:].std() == pytest.approx(want, rel=0.15)


def test_joint_step_numpy_torch_and_batch_agree():
    rng = np.random.default_rng(0)
    B = 64
    pos = rng.uniform(0.0, ROOM_SIZE, size=(B, 2, 2))
    state = np.concatenate([pos, rng.uniform(-1, 1, size=(B, 2, 2))], -1)
    cmd = rng.uniform(-1, 1, size=(B, 2, 2))
    active = rng.random((B, 2)) < 0.8
    noise = 0.02 * rng.standard_normal((B, 2, 2))
    dyn = DroneDynamics()
    for constrained in (True, False):
        r_np = joint_step(state, cmd, active, noise, dynamics=dyn, constrained=constrained)
        r_t = joint_step(*(torch.as_tensor(x) for x in (state, cmd, active, noise)),
                         dynamics=dyn, constrained=constrained)
        for f in ("state", "active", "violated", "reached", "collision"):
            np.testing.assert_allclose(getattr(r_t, f).numpy(), getattr(r_np, f), err_msg=f)
        for b in range(0, B, 9):  # a batch entry equals the unbatched step
            one = joint_step(state[b], cmd[b], active[b], noise[b], dynamics=dyn,
                             constrained=constrained)
            np.testing.assert_array_equal(one.state, r_np.state[b])
            np.testing.assert_array_equal(one.violated, r_np.violated[b])
        # Inactive drones do not move.
        np.testing.assert_array_equal(r_np.state[~active], state[~active])


def _step_variants(rng, pos, vel):
    """``(dynamics, (state, command, active, noise))`` for a batch of drones at ``pos``
    with ``vel`` (both ``[B, 2, 2]``): random commands past the bounds and 80 % of the
    drones flying; the box and the disc, without and with noise, numpy and torch."""
    B = len(pos)
    state = np.concatenate([pos, vel], -1)
    cmd = rng.uniform(-1.3, 1.3, size=(B, 2, 2))
    active = rng.random((B, 2)) < 0.8
    noise = 0.02 * rng.standard_normal((B, 2, 2))
    for dyn in (DroneDynamics(), DroneDynamics(command_set="disc", max_speed=1.5)):
        for args in ((state, cmd, active, None), (state, cmd, active, noise)):
            yield dyn, args
            yield dyn, tuple(None if a is None else torch.as_tensor(a) for a in args)


def test_nominal_step_equals_the_nominal_joint_step_bit_for_bit():
    # The planner's model must be the nominal game exactly: same states (signed zeros
    # too) and the same drones still flying, arrivals and walls included.
    rng = np.random.default_rng(1)
    B = 512
    pos = rng.uniform(0.0, ROOM_SIZE, size=(B, 2, 2))
    pos[: B // 2, :, 1] = rng.uniform(ROOM_SIZE - 0.6, ROOM_SIZE, size=(B // 2, 2))  # doors
    for dyn, x in _step_variants(rng, pos, rng.uniform(-1.5, 1.5, size=(B, 2, 2))):
        full = joint_step(*x, dynamics=dyn, constrained=False)
        lean_state, lean_active = nominal_step(*x, dynamics=dyn)
        assert (np.asarray(full.reached).any()
                and not np.asarray(full.active).all())  # arrivals were tested
        np.testing.assert_array_equal(np.asarray(lean_state), np.asarray(full.state))
        np.testing.assert_array_equal(np.signbit(np.asarray(lean_state)),
                                      np.signbit(np.asarray(full.state)))
        np.testing.assert_array_equal(np.asarray(lean_active), np.asarray(full.active))



def _reference_joint_step(state, command, active, noise, dyn, constrained):
    """joint_step written plainly with wheres (the shape it had before the planner's
    speed-up): the independent truth for the exact products and in-place rows."""
    lib = torch if isinstance(state, torch.Tensor) else np
    where = torch.where if lib is torch else np.where
    pos, vel = state[..., :2], state[..., 2:]
    if dyn.command_set == "box":
        u = lib.clip(command, -1.0, 1.0)
    else:
        norm = (command * command).sum(-1, keepdims=True) ** 0.5
        u = command / lib.clip(norm, 1.0, np.inf)
    v = vel + (dyn.dt / dyn.tau) * (u * dyn.max_speed - vel)
    if noise is not None:
        v = v + noise
    v = lib.clip(v, -dyn.vel_limit, dyn.vel_limit)
    free = pos + dyn.dt * v
    p = lib.clip(free, 0.0, ROOM_SIZE)
    v = where(p == free, v, v * 0.0)
    p, v = where(active[..., None], p, pos), where(active[..., None], v, vel)
    door = lib.asarray(DOORS, dtype=lib.float64) if lib is np else torch.tensor(DOORS).to(p)
    at_door = ((p[..., 0] >= door[:, 0]) & (p[..., 0] <= door[:, 1])
               & (p[..., 1] >= ROOM_SIZE - DOOR_DEPTH) & active)
    gap = p[..., 0, :] - p[..., 1, :]
    collision = ((gap * gap).sum(-1) < PROXIMITY_RADIUS**2) & active[..., 0] & active[..., 1]
    violated = (in_obstacle(p) & active) | collision[..., None]
    stop = (violated | at_door) if constrained else at_door
    v = where(stop[..., None], v * 0.0, v)
    cat = torch.cat if lib is torch else np.concatenate
    return cat([p, v], -1), active & ~stop


def test_joint_step_equals_a_plain_where_reference_bit_for_bit():
    # The step multiplies by 0/1 masks and assigns kept-back rows in place (numpy's
    # broadcast where is slow on a planner's batches): values and signed zeros must be
    # those of the plain wheres, in both games, numpy and torch.
    rng = np.random.default_rng(4)
    B = 600
    pos = rng.uniform(-0.2, ROOM_SIZE + 0.2, size=(B, 2, 2))
    pos[: B // 3, :, 1] = rng.uniform(ROOM_SIZE - 0.6, ROOM_SIZE, size=(B // 3, 2))  # doors
    pos[B // 3: B // 2, 1] = pos[B // 3: B // 2, 0] + 0.1  # collisions
    vel = rng.uniform(-1.5, 1.5, size=(B, 2, 2))
    vel[::7] = -0.0
    for dyn, x in _step_variants(rng, pos, vel):
        for constrained in (True, False):
            ref_state, ref_active = _reference_joint_step(*x, dyn, constrained)
            got = joint_step(*x, dynamics=dyn, constrained=constrained)
            np.testing.assert_array_equal(np.asarray(got.state), np.asarray(ref_state))
            np.testing.assert_array_equal(np.signbit(np.asarray(got.state)),
                                          np.signbit(np.asarray(ref_state)))
            np.testing.assert_array_equal(np.asarray(got.active), np.asarray(ref_active))


# ---- constraints ------------------------------------------------------------------
@pytest.mark.parametrize("constrained", [True, False])
def test_obstacle_violation_freezes_only_in_true_game(constrained):
    env = arena([[4.5, 4.4], [8.0, 1.0]], constrained=constrained)
    infos = fly(env, {D0: (0.0, 1.0)}, 15)
    hit = next(t for t, i in enumerate(infos) if i.get(D0, {}).get("violated"))
    assert infos[hit][D0]["in_obstacle"] and not infos[hit][D1]["violated"]
    if constrained:
        assert D0 not in env.agents and env.violated[0] and not env.active[0]
        frozen = env.state()[0]
        assert np.all(frozen[2:] == 0.0) and in_obstacle(frozen[:2])
        fly(env, {D1: (0.0, 0.5)}, 5)
        np.testing.assert_array_equal(env.state()[0], frozen)
    else:
        assert D0 in env.agents and env.violated[0]
        y = env.state()[0, 1]
        fly(env, {D0: (0.0, 1.0)}, 5)
        assert env.state()[0, 1] > y + 0.3  # flies on through the obstacle


@pytest.mark.parametrize("constrained", [True, False])
def test_walls_stop_drones_and_only_the_own_door_lets_one_out(constrained):
    # drone 0 pushes into the left wall; drone 1 into the top wall at drone 0's door:
    # the walls stop both (position on the wall, velocity into it 0), no violation.
    env = arena([[0.3, 2.0], [8.75, 9.2]], constrained=constrained)
    infos = fly(env, {D0: (-1.0, 0.0), D1: (0.0, 1.0)}, 10)
    assert not any(i[a]["violated"] for i in infos for a in (D0, D1))
    state = env.state()
    assert state[0, 0] == 0.0 and state[0, 2] == 0.0 and state[0, 1] == pytest.approx(2.0, abs=0.2)
    assert state[1, 1] == ROOM_SIZE and state[1, 3] == 0.0
    assert not env.reached.any() and env.agents == [D0, D1]
    fly(env, {D0: (1.0, 0.0)}, 5)  # and leaves the wall again
    assert env.state()[0, 0] > 0.1
    # drone 0 through its own door: success, reward 1, done in both games.
    env = arena([[8.75, 9.0], [1.25, 5.5]], constrained=constrained)
    rewards = []
    for _ in range(20):
        if D0 not in env.agents:
            break
        _, r, term, _, info = env.step({a: np.array([0.0, 1.0]) for a in env.agents})
        rewards.append(r[D0])
    assert term[D0] and info[D0]["reached"] and not info[D0]["violated"]
    assert rewards[-1] == 1.0 and sum(rewards) == 1.0
    assert env.state()[0, 1] >= ROOM_SIZE - DOOR_DEPTH and env.state()[0, 1] <= ROOM_SIZE


@pytest.mark.parametrize("constrained", [True, False])
def test_collision_detected(constrained):
    env = arena([[4.0, 2.0], [6.0, 2.0]], constrained=constrained)
    infos = fly(env, {D0: (1.0, 0.0), D1: (-1.0, 0.0)}, 30)
    t = next(t for t, i in enumerate(infos) if i[D0]["collision"])
    assert infos[t][D1]["collision"] and infos[t][D0]["violated"] and infos[t][D1]["violated"]
    assert np.linalg.norm(env.trajectory()[t + 1, 0] - env.trajectory()[t + 1, 1]) \
        < PROXIMITY_RADIUS
    assert np.all(np.linalg.norm(env.trajectory()[:t + 1, 0] - env.trajectory()[:t + 1, 1],
                                 axis=-1) >= PROXIMITY_RADIUS)
    assert (env.agents == []) == constrained


def test_bad_input_is_rejected_with_fix():
    with pytest.raises(ValueError, match="max_steps"):
        DroneArena(max_steps=0)
    with pytest.raises(ValueError, match="dt <= tau"):
        DroneDynamics(dt=0.5, tau=0.3)
    env = DroneArena()
    with pytest.raises(ValueError, match="obstacles"):
        env.reset(options={"positions": [[5.0, 5.5], [8.0, 1.0]]})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="No action"):
        env.step({D0: np.zeros(2)})
    with pytest.raises(ValueError, match=r"\[2\] velocity command"):
        env.step({D0: np.zeros(3), D1: np.zeros(2)})
    with pytest.raises(ValueError, match="Unknown agent"):
        env.observation_space("drone_7")


def test_grid_and_arena_refuse_the_same_call_mistakes_with_the_same_messages():
    from dicrl_torch.envs.grid import GridLayout
    from dicrl_torch.envs.gridworld_env import GridWorldCMG

    messages = []
    for env, action in ((GridWorldCMG(layout=GridLayout.scobee(2)), 0),
                        (DroneArena(), np.zeros(2))):
        said = []
        with pytest.raises(RuntimeError, match="before reset") as err:
            env.step(dict.fromkeys(env.possible_agents, action))
        said.append(str(err.value))
        with pytest.raises(RuntimeError, match="before reset") as err:
            env.state()
        said.append(str(err.value))
        env.reset(seed=0)
        first, second = env.possible_agents
        for actions in ({first: action}, {first: action, second: action, "ghost": action}):
            with pytest.raises(ValueError) as err:
                env.step(actions)
            said.append(str(err.value).replace(repr(env.possible_agents), "AGENTS")
                        .replace(second, "SECOND"))
        messages.append(said)
    assert messages[0] == messages[1]
    assert "No action given" in messages[0][2] and "Unknown agent 'ghost'" in messages[0][3]


def test_render_returns_image():
    env = DroneArena(render_mode="rgb_array")
    env.reset(seed=0)
    fly(env, {D0: (0.5, 0.5), D1: (-0.5, 0.5)}, 10)
    env.set_constraint_overlay(CellOccupancyCostBasis().true_constraints())
    img = env.render()
    assert img.dtype == np.uint8 and img.shape == (320, 320, 3)
    env.set_constraint_overlay([cell(4, 6), cell(5, 6)])
    assert env.render().shape == (320, 320, 3)
    with pytest.raises(ValueError, match="Constraint cells"):
        env.set_constraint_overlay([100])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert DroneArena().render() is None


# ---- demonstrations -----------------------------------------------------------------
@pytest.fixture(scope="module")
def demos() -> DroneDemonstrations:
    return make_drone_demonstrations(9, rng=np.random.default_rng(0))


def test_drone_pairs_convert_to_continuous_demonstrations(demos):
    """What a solver of any continuous game reads: the same arrays, and each drone's
    acting steps (its commands after it reached its door are ignored by the env)."""
    c = demos.to_continuous()
    assert (c.n_agents, c.state_dim, c.action_dim) == (2, 4, 2) and c.agent_names == AGENTS
    assert np.array_equal(c.states, demos.states) and np.array_equal(c.actions, demos.actions)
    assert np.array_equal(c.lengths, demos.lengths) and np.array_equal(c.seeds, demos.seeds)
    acted = demos.drone_lengths()
    assert not (acted == demos.lengths[:, None]).all()  # some drone arrives before its mate
    assert np.array_equal(c.agent_lengths, acted)
    assert np.array_equal(c.acting_mask(),
                          np.arange(demos.horizon)[None, :, None] < acted[:, None, :])


def test_demonstrations_reach_doors_without_violation(demos):
    assert demos.n_pairs == 9 and demos.states.shape == (9, demos.horizon + 1, 2, 4)
    assert demos.actions.shape == (9, demos.horizon, 2, 2) and demos.lengths.max() == \
        demos.horizon
    for k in range(demos.n_pairs):
        states, env = replay_pair(demos, k)
        n = demos.lengths[k]
        np.testing.assert_array_equal(states, demos.states[k, :n + 1])
        assert env.reached.all() and not env.violated.any() and not env.agents
        # The same actions in the nominal game report no violation either.
        _, nominal = replay_pair(demos, k, constrained=False)
        assert nominal.reached.all() and not nominal.violated.any()
    # No demonstrated state touches a true constraint feature: zero true cost.
    basis = CellOccupancyCostBasis()
    cost = basis(demos.states) @ basis.true_weights()  # numpy in, read-only
    assert float(cost.max()) == 0.0


def test_demonstrations_fly_in_the_given_dynamics():
    """The planner flies its pairs in the learners' dynamics: under the disc every
    recorded command is one the disc flies unchanged, and replaying it in the same
    dynamics gives the recorded states."""
    disc = DroneDynamics(command_set="disc", max_speed=1.5)
    pairs = make_drone_demonstrations(3, rng=np.random.default_rng(1), dynamics=disc)
    norms = np.linalg.norm(pairs.actions, axis=-1)
    assert norms.max() <= 1 + 1e-12 and norms.max() > 0.5
    for k in range(pairs.n_pairs):
        states, env = replay_pair(pairs, k, dynamics=disc)
        np.testing.assert_array_equal(states, pairs.states[k, :pairs.lengths[k] + 1])
        assert env.reached.all() and not env.violated.any()


def test_demonstrations_are_seeded_and_varied(demos):
    again = make_drone_demonstrations(2, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(again.seeds, demos.seeds[:2])
    for k in range(2):  # the same pairs, padded to a different horizon
        n = demos.lengths[k]
        assert again.lengths[k] == n
        np.testing.assert_array_equal(again.states[k, :n + 1], demos.states[k, :n + 1])
        np.testing.assert_array_equal(again.actions[k, :n], demos.actions[k, :n])
    # Randomised via-points and timing: no two pairs fly the same path.
    assert len(set(demos.lengths.tolist())) > 3
    with pytest.raises(TypeError, match="default_rng"):
        make_drone_demonstrations(2, rng=0)


def _cells_on_segment(a: np.ndarray, b: np.ndarray) -> set[int]:
    pts = a + np.linspace(0.0, 1.0, 2001)[:, None] * (b - a)
    ix = np.clip(np.floor(pts / CELL_SIZE).astype(int), 0, GRID_CELLS - 1)
    return {int(iy * GRID_CELLS + jx) for jx, iy in ix}


def test_block_cells_are_identifiable_from_the_pairs(demos):
    """The arena is built so that the demonstrations identify the true cells: the
    straight route from any start (jitter included) to the centre of the own door crosses
    every block cell (the unconstrained policy would enter them), and the 9 pairs
    together visit every other cell the route from the nominal start crosses (so the
    block is the only explanation of the detours)."""
    block = set(np.flatnonzero(obstacle_cell_mask()).tolist())
    basis = CellOccupancyCostBasis()
    visits = np.zeros(basis.dim)
    for k in range(demos.n_pairs):
        n = demos.lengths[k]
        visits += basis(demos.states[k, :n]).sum(0).numpy()
    jitter = START_JITTER * np.array([[0, 0], [-1, -1], [-1, 1], [1, -1], [1, 1]])
    for i, start in enumerate(NOMINAL_STARTS):
        door = np.array([np.mean(DOORS[i]), ROOM_SIZE])
        routes = [_cells_on_segment(np.asarray(start) + d, door) for d in jitter]
        assert all(cells >= block for cells in routes), f"drone {i}: a route misses a cell"
        free_on_routes = routes[0] - block  # from the nominal start
        unvisited = [c for c in free_on_routes if visits[i * GRID_CELLS**2 + c] == 0]
        assert unvisited == [], f"drone {i}: no pair visits the route cells {unvisited}"
        assert all(visits[i * GRID_CELLS**2 + c] == 0 for c in block)


def test_planner_paths_keep_clearance():
    assert path_clearance(np.array([[3.0, 5.5], [7.0, 5.5]]), 0) == 0.0  # through the block
    assert path_clearance(np.array([[5.0, 2.0], [5.0, 4.0]]), 0) == pytest.approx(1.0)


def test_round_trip(tmp_path, demos):
    path = save_drone_demonstrations(tmp_path / "sub" / "drones.npz", demos)
    back = load_drone_demonstrations(path, n_pairs=9, dt=0.1)
    assert back == demos and back.seeds is not None
    unseeded = DroneDemonstrations(demos.states, demos.actions, demos.lengths, demos.dt)
    assert load_drone_demonstrations(
        save_drone_demonstrations(tmp_path / "u.npz", unseeded)) == unseeded
    with pytest.raises(ValueError, match=re.escape("drones.npz") + ".*n_pairs"):
        load_drone_demonstrations(path, n_pairs=8)
    with pytest.raises(FileNotFoundError):
        load_drone_demonstrations(tmp_path / "missing.npz")


def _fields(demos: DroneDemonstrations) -> dict:
    return {"states": np.array(demos.states), "actions": np.array(demos.actions),
            "lengths": np.array(demos.lengths), "dt": np.float64(0.1),
            "format_version": np.int64(1)}


def _nan_states(f):
    f["states"][1, 3, 0, 2] = np.nan


def _out_of_room(f):
    f["states"][2, 5, 1, 0] = -0.5


def _padding(f):
    f["lengths"][0] -= 3


BAD_FILES = {
    "int-states": ("states", lambda f: f.update(states=f["states"].astype(np.int64))),
    "nan": ("states", _nan_states),
    "object": ("actions", lambda f: f.update(actions=f["actions"].astype(object))),
    "shape": ("actions", lambda f: f.update(actions=f["actions"][:, :-1])),
    "states-3d": ("states", lambda f: f.update(states=f["states"][..., 0])),
    "out-of-room": ("states", _out_of_room),
    "big-action": ("actions", lambda f: f["actions"].__setitem__((0, 0, 0, 0), 1.5)),
    "float-lengths": ("lengths", lambda f: f.update(lengths=f["lengths"] * 1.0)),
    "long": ("lengths", lambda f: f["lengths"].__setitem__(0, 10_000)),
    "padding": ("lengths", _padding),
    "dt": ("dt", lambda f: f.update(dt=np.float64(-0.1))),
    "dt-int": ("dt", lambda f: f.update(dt=np.int64(1))),
    "missing": ("lengths", lambda f: f.pop("lengths")),
    "unknown": ("extra", lambda f: f.update(extra=np.zeros(2))),
    "version": ("format_version", lambda f: f.update(format_version=np.int64(2))),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_malformed_files_are_rejected(tmp_path, demos, case):
    field, mutate = BAD_FILES[case]
    f = _fields(demos.subset([0, 1, 2]))
    mutate(f)
    assert_file_refused(load_drone_demonstrations, tmp_path / f"bad_{case}.npz", f, field)


def test_not_an_archive(tmp_path):
    assert_not_an_archive(load_drone_demonstrations, tmp_path)


def test_partition_4_5(demos):
    assert isinstance(demos, Trajectories) and demos.n_trajectories == demos.n_pairs == 9
    a, b = partition_demonstrations(demos, PAPER_DRONE_SPLIT)
    assert isinstance(a, DroneDemonstrations)
    assert (a.n_pairs, b.n_pairs) == PAPER_DRONE_SPLIT
    assert a == demos.subset(range(4)) and b == demos.subset(range(4, 9))
    parts = partition_demonstrations(demos, PAPER_DRONE_SPLIT, rng=np.random.default_rng(1))
    seeds = np.concatenate([p.seeds for p in parts])
    assert sorted(seeds.tolist()) == sorted(demos.seeds.tolist())
    # the same shuffle as the grid world's trajectories (one partition function)
    order = np.random.default_rng(1).permutation(9)
    assert parts[0] == demos.subset(order[:4]) and parts[1] == demos.subset(order[4:])
    with pytest.raises(ValueError, match="sum to 8, but there are 9 pairs"):
        partition_demonstrations(demos, (4, 4))
    with pytest.raises(TypeError, match="Trajectories"):
        partition_demonstrations(demos.states, PAPER_DRONE_SPLIT)


def test_drone_demonstrations_equality_and_subsets(demos):
    same = DroneDemonstrations(states=demos.states, actions=demos.actions,
                               lengths=demos.lengths, dt=demos.dt, seeds=demos.seeds)
    assert same == demos and same != demos.subset(range(8))
    unseeded = DroneDemonstrations(states=demos.states, actions=demos.actions,
                                   lengths=demos.lengths, dt=demos.dt)
    assert unseeded != demos and demos != unseeded and unseeded.subset([1, 0]).seeds is None
    assert demos.subset([2, 0]).lengths.tolist() == demos.lengths[[2, 0]].tolist()
    with pytest.raises(TypeError, match="unhashable"):
        hash(demos)


# ---- features -----------------------------------------------------------------------
def test_cell_basis_shapes_values_and_true_constraints():
    basis = CellOccupancyCostBasis()
    assert basis.dim == 201 and list(basis.parameters()) == []
    states = torch.zeros(3, 2, 4, dtype=torch.float64)
    states[0, :, :2] = torch.tensor([[4.5, 6.5], [0.2, 9.9]])
    states[1, :, :2] = torch.tensor([[5.0, 5.0], [5.3, 5.0]])  # 0.3 m apart
    states[2, :, :2] = torch.tensor([[10.0, -0.5], [3.999, 2.0]])  # border, outside
    phi = basis(states)
    assert phi.shape == (3, 201) and phi.dtype == torch.float64
    assert torch.all(phi[:, :200].sum(-1) == 2)
    assert phi[0, cell(4, 6)] == 1 and phi[0, 100 + cell(0, 9)] == 1
    assert phi[1, cell(5, 5)] == 1 and phi[1, 100 + cell(5, 5)] == 1
    assert phi[2, cell(9, 0)] == 1 and phi[2, 100 + cell(3, 2)] == 1
    assert phi[:, 200].tolist() == [0.0, 1.0, 0.0]
    true = basis.true_constraints()
    assert true.shape == (201,) and true[200]
    for i in range(2):
        block = true[i * 100:(i + 1) * 100]
        assert block[cell(4, 5)] and block[cell(5, 5)]  # inside the central block
        assert not block[cell(1, 1)] and not block[cell(9, 1)]  # the start cells
        for touching in [cell(3, 5), cell(6, 5), cell(4, 4), cell(5, 6), cell(3, 4)]:
            assert not block[touching]
        assert int(block.sum()) == 2
    assert torch.equal(true[:100], torch.from_numpy(obstacle_cell_mask()))
    # Batched leading dims, float32 and numpy input.
    assert basis(np.zeros((4, 5, 2, 4))).shape == (4, 5, 201)
    assert basis(torch.zeros(2, 2, 4, dtype=torch.float32)).dtype == torch.float32


def test_rbf_basis_matches_cell_constraints():
    rbf = RBFCostBasis()
    cells = CellOccupancyCostBasis()
    assert rbf.dim == 201 and list(rbf.parameters()) == []
    assert torch.equal(rbf.true_constraints(), cells.true_constraints())
    rng = np.random.default_rng(0)
    states = torch.as_tensor(rng.uniform(0, ROOM_SIZE, size=(500, 2, 4)))
    phi = rbf(states)
    assert phi.shape == (500, 201) and phi.min() >= 0 and phi.max() <= 1
    coarse = RBFCostBasis(n_per_axis=5, width=1.5)
    assert coarse.dim == 51 and coarse(states).shape == (500, 51)


def test_reward_bases():
    door = DoorLocationRewardBasis(coefficient=2.0)
    assert door.dim == 4 and door.max_value == 2.0 and list(door.parameters()) == []
    at_start = torch.tensor([[[*NOMINAL_STARTS[0], 0, 0], [*NOMINAL_STARTS[1], 0, 0]]])
    at_door = torch.tensor([[[8.75, 10.0, 0, 0], [1.25, 10.0, 0, 0]]])
    f0, f1 = door(at_start)[0], door(at_door)[0]
    assert f0[0] == 0 and f0[2] == 0  # progress 0 at the start
    assert f1.tolist() == [2.0, 2.0, 2.0, 2.0]  # progress and closeness full at the door
    rng = np.random.default_rng(0)
    states = torch.as_tensor(rng.uniform(-1, 11, size=(500, 2, 4)))
    phi = door(states)
    assert phi.min() >= 0 and phi.max() <= 2.0
    # Oriented towards the door: moving drone 0 towards its door raises both features.
    closer = at_start.clone()
    closer[0, 0, :2] += torch.tensor([1.0, 1.0])
    assert torch.all(door(closer)[0, :2] > f0[:2])
    fourier = FourierRewardBasis(order=2)
    assert fourier.dim == 18
    phi = fourier(states)
    assert phi.shape == (500, 18) and phi.min() >= 0 and phi.max() <= 1
    assert torch.all(phi[:, 0] == 1)  # the constant term


def test_exponential_closeness_against_direct_formula():
    """closeness='exponential' is exp(-|p - g| / length) outside the door, and makes the
    top corner beside a door earn clearly less than the door (the linear shape: 0.91)."""
    basis = DoorLocationRewardBasis(closeness="exponential", closeness_length=1.5)
    rng = np.random.default_rng(1)
    states = rng.uniform(0, ROOM_SIZE, size=(300, 2, 4))
    states[..., 1] = np.minimum(states[..., 1], 9.0)  # below the doors' mouths
    phi = basis(states).numpy().reshape(300, 2, 2)
    doors = np.array([[8.75, 10.0], [1.25, 10.0]])
    dist = np.linalg.norm(states[..., :2] - doors, axis=-1)
    np.testing.assert_allclose(phi[..., 1], np.exp(-dist / 1.5), rtol=1e-12)
    np.testing.assert_allclose(phi[..., 0], DoorLocationRewardBasis()(states).numpy()
                               .reshape(300, 2, 2)[..., 0])  # progress is unchanged
    corners = torch.tensor([[[10.0, 10.0, 0, 0], [0.0, 10.0, 0, 0]]], dtype=torch.float64)
    assert DoorLocationRewardBasis()(corners)[0, 1] > 0.9
    assert basis(corners)[0, 1] < 0.5 and basis(corners)[0, 3] < 0.5
    at_door = torch.tensor([[[8.75, 10.0, 0, 0], [1.25, 10.0, 0, 0]]], dtype=torch.float64)
    assert basis(at_door)[0].tolist() == [1.0, 1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="closeness must be one of"):
        DoorLocationRewardBasis(closeness="cubic")
    with pytest.raises(ValueError, match="closeness_length"):
        DoorLocationRewardBasis(closeness="exponential", closeness_length=0)


def _planner_states(rng, n: int) -> np.ndarray:
    """``[n, 2, 4]`` joint states with positions on cell borders, in the doors' mouths,
    outside the room and close together, besides uniform ones."""
    states = rng.uniform(-0.5, ROOM_SIZE + 0.5, size=(n, 2, 4))
    k = n // 4
    states[:k, :, :2] = rng.integers(0, 11, (k, 2, 2)) + rng.choice([0.0, 0.1, -0.1], (k, 2, 2))
    states[k:2 * k, :, 0] = rng.choice([d for door in DOORS for d in door], (k, 2))
    states[k:2 * k, :, 1] = rng.choice([ROOM_SIZE - DOOR_DEPTH, 9.8, 10.0, 9.0], (k, 2))
    states[2 * k:3 * k, 1, :2] = states[2 * k:3 * k, 0, :2] + rng.uniform(-0.4, 0.4, (k, 2))
    return states


@pytest.mark.parametrize("closeness", ["linear", "exponential"])
def test_door_features_numpy_path_equals_compute_bit_for_bit(closeness):
    basis = DoorLocationRewardBasis(coefficient=1.5, closeness=closeness)
    states = _planner_states(np.random.default_rng(2), 4000).reshape(20, 200, 2, 4)
    fast = basis.numpy_features(states)
    assert fast.shape == (20, 200, 4) and fast.dtype == np.float64
    np.testing.assert_array_equal(fast, basis.compute(torch.as_tensor(states)).numpy())


@pytest.mark.parametrize("margin", [0.0, 0.1, 0.3])
def test_cell_basis_dot_is_the_features_weighted_sum(margin):
    basis = CellOccupancyCostBasis(margin=margin)
    rng = np.random.default_rng(3)
    states = _planner_states(rng, 4000).reshape(40, 100, 2, 4)
    phi = basis.compute(torch.as_tensor(states)).numpy()  # [40, 100, 201]
    weights = rng.normal(size=201)
    np.testing.assert_allclose(basis.dot(states, weights), phi @ weights, rtol=0,
                               atol=1e-12)
    # The planner's test "enters a learned constraint": dot with a 0/1 mask > 0.
    mask = rng.random(201) < 0.2
    np.testing.assert_array_equal(basis.dot(states, mask.astype(float)) > 0,
                                  (phi[..., mask] > 0).any(-1))


def test_feature_input_checks():
    basis = CellOccupancyCostBasis()
    with pytest.raises(ValueError, match=r"\[\.\.\., 2, 4\]"):
        basis(torch.zeros(3, 4))
    with pytest.raises(ValueError, match="NaN"):
        basis(torch.full((1, 2, 4), float("nan")))
    with pytest.raises(ValueError, match="float"):
        basis(torch.zeros(1, 2, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match="do not match"):
        basis(torch.zeros(3, 2, 4), torch.zeros(2, 2, 2))
    assert basis(torch.zeros(3, 2, 4), torch.zeros(3, 2, 2)).shape == (3, 201)
    with pytest.raises(ValueError, match="coefficient"):
        DoorLocationRewardBasis(coefficient=0)
    with pytest.raises(ValueError, match="n_per_axis"):
        RBFCostBasis(n_per_axis=0)


def test_render_arena_with_demonstrations(demos):
    img = render_arena(
        trajectories=[demos.states[k, :demos.lengths[k] + 1, :, :2] for k in range(3)],
        constraint_cells=CellOccupancyCostBasis().true_constraints(), title="demos")
    assert img.shape == (320, 320, 3) and img.dtype == np.uint8
    assert len(OBSTACLES) == 1


@pytest.mark.parametrize("basis", [CellOccupancyCostBasis(), RBFCostBasis(n_per_axis=3),
                                   DoorLocationRewardBasis(), FourierRewardBasis(order=1)])
def test_drone_shares_give_each_feature_to_its_drone(basis):
    shares = basis.drone_shares()
    assert shares.shape == (basis.dim, 2) and torch.all(shares.sum(1) == 1.0)
    for name, row in zip(basis.names, shares, strict=True):
        if name.startswith("drone0/"):
            assert row.tolist() == [1.0, 0.0]
        elif name.startswith("drone1/"):
            assert row.tolist() == [0.0, 1.0]
        else:  # shared by both drones: the proximity
            assert name == "proximity" and row.tolist() == [0.5, 0.5]
    stray = DoorLocationRewardBasis()
    stray.names = [*stray.names[:-1], "drone2/closeness"]
    with pytest.raises(ValueError, match="beyond the 2 of the game"):
        stray.drone_shares()
