"""The constrained spread's batched joint env (dicrl_torch/envs/mpe/vector.py) against
its reference, :class:`EnvList` over ``spread_joint_env`` (the game stepped by mpe2's
own ``World.step``), transition for transition."""

from __future__ import annotations

import functools
import io

import numpy as np
import pytest
import torch

from dicrl_torch.envs.joint import JointAgentEnv
from dicrl_torch.envs.mpe import ConstrainedSpread, SpreadLayout, SpreadVectorEnv
from dicrl_torch.runs.mpe import spread_joint_env
from dicrl_torch.solvers.sac.env_list import EnvList, vector_env_of

# Tolerance on the float64 states: the batched step replays mpe2's and the env's
# operations in their order (forces summed in mpe2's pair order, norms as numpy's norm
# of a [2] vector computes them), and the difference measured on every step of these
# tests is exactly 0; 1e-12 leaves room for a numpy whose vectorised loops round a
# last bit differently. Observations are float32 copies of the states (1 float32 ulp);
# the flags must be equal.
STATE_ATOL = 1e-12
OBS_ATOL = 1e-6
MAX_STEPS = 15
SEEDS = [5, 6, 7]
THREE = SpreadLayout(n_agents=3)
CORNER = -1.5  # SpreadLayout's arena_half_width


def _pair(n_envs: int, **kwargs):
    """The batched env and its reference, for ``spread_joint_env(**kwargs)``."""
    make = functools.partial(spread_joint_env, max_steps=MAX_STEPS, **kwargs)
    vec = make().vector_env(n_envs)
    assert isinstance(vec, SpreadVectorEnv)
    return vec, EnvList(make, n_envs)


def _actions(states: np.ndarray, layout: SpreadLayout, rng: np.random.Generator
             ) -> np.ndarray:
    """``[n, 2 N]`` joint actions, often outside ``[-1, 1]``: slot 0 drives every agent at
    the disc's centre (the disc, and agents pushed into each other there), slot 1 into
    the lower-left corner (the walls), slot 2 at its landmark (covering at the end);
    each with a random part."""
    pos, vel = states[..., :2], states[..., 2:]
    targets = np.stack([np.zeros_like(pos[0]), np.full_like(pos[1], CORNER),
                        layout.landmark_array])
    to = targets - pos
    heading = 1.4 * to / np.maximum(np.linalg.norm(to, axis=-1, keepdims=True), 1e-9)
    heading[2] = 6.0 * to[2] - 1.5 * vel[2]  # a PD controller that settles on the landmark
    a = heading + rng.uniform(-0.6, 0.6, size=heading.shape) * [[[1.0]], [[1.0]], [[0.1]]]
    return a.reshape(len(states), -1)


def _assert_same(got, want, where: str) -> None:
    """Every field of two VectorSteps equal (states within STATE_ATOL)."""
    np.testing.assert_allclose(got.states, want.states, rtol=0, atol=STATE_ATOL,
                               err_msg=where)
    for field in ("obs", "final_obs"):
        a, b = getattr(got, field), getattr(want, field)
        assert a.dtype == b.dtype == np.float32, where
        np.testing.assert_allclose(a, b, rtol=0, atol=OBS_ATOL, err_msg=f"{where} {field}")
    for field in ("terminated", "truncated", "reached", "violated"):
        a, b = getattr(got, field), getattr(want, field)
        assert a.dtype == bool and np.array_equal(a, b), f"{where} {field}: {a} != {b}"


@pytest.mark.parametrize("layout", [SpreadLayout(), THREE], ids=["two", "three"])
@pytest.mark.parametrize("noise_std", [0.0, 0.05], ids=["exact", "noisy"])
@pytest.mark.parametrize("constrained", [True, False], ids=["true", "nominal"])
def test_batched_equals_reference(constrained, noise_std, layout):
    vec, ref = _pair(3, constrained=constrained, layout=layout, noise_std=noise_std)
    assert (vec.n_envs, vec.n_agents, vec.state_shape) == \
        (ref.n_envs, ref.n_agents, ref.state_shape)
    assert vec.observation_space == ref.observation_space
    assert vec.action_space == ref.action_space
    obs, states = vec.reset(SEEDS)
    ref_obs, ref_states = ref.reset(SEEDS)
    np.testing.assert_array_equal(states, ref_states)
    np.testing.assert_array_equal(obs, ref_obs)
    rng = np.random.default_rng(0)
    outside = contacts = walls = terminated = ends = reached = violated = 0
    for t in range(40):
        if t == 20:  # a solver's clone swaps a slot's stream mid-episode
            vec.set_rng(1, np.random.default_rng(99))
            ref.set_rng(1, np.random.default_rng(99))
        actions = _actions(ref_states, layout, rng)
        outside += int(np.any(np.abs(actions) > 1))
        flying = np.stack([env.get_wrapper_attr("env").active for env in ref.envs])
        pos = ref_states[..., :2]
        gap = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
        both = flying[:, :, None] & flying[:, None, :] & ~np.eye(layout.n_agents, dtype=bool)
        contacts += int(np.any(both & (gap < 0.3)))  # mpe2's agents touch at 2 * 0.15
        got, want = vec.step(actions), ref.step(actions)
        _assert_same(got, want, f"step {t}")
        walls += int(np.any(np.abs(want.states[..., :2]) == 1.5))
        terminated += int(want.terminated.sum())
        ends += int(want.done.sum())
        reached += int(want.reached.sum())
        violated += int(want.violated.sum())
        ref_states = np.stack([env.get_wrapper_attr("env").state() for env in ref.envs])
    # the test is not vacuous: clipped commands, walls, violations and resets happened,
    # freezing in the true game, contact (and covering) in the nominal one
    assert outside and walls and violated and ends >= 3
    if constrained:
        assert terminated  # every agent of an episode froze
    else:
        assert contacts and reached and not terminated


@pytest.mark.parametrize("constrained", [True, False], ids=["true", "nominal"])
def test_agents_at_one_point(constrained):
    """Two agents pushed into the same corner of the walls sit at one point, where mpe2's
    contact force divides by 0; both envs make it zero."""
    vec, ref = _pair(1, constrained=constrained)
    vec.reset([3])
    ref.reset([3])
    game = ref.envs[0].get_wrapper_attr("env")
    for agent in game._world.agents:
        agent.state.p_pos = np.full(2, CORNER)
        agent.state.p_vel = np.full(2, -1.0)
    vec._pos[:] = CORNER
    vec._vel[:] = -1.0
    push = np.full((1, 4), -1.0)
    for t in range(3):
        got, want = vec.step(push), ref.step(push)
        assert np.all(np.isfinite(got.states))
        _assert_same(got, want, f"step {t}")
        if t == 0:  # the contact was at one point: both still there (or frozen there)
            assert np.all(want.states[0, :, :2] == CORNER)


def test_state_dict_round_trip():
    vec, ref = _pair(3, constrained=True, noise_std=0.05)
    vec.reset(SEEDS)
    _, states = ref.reset(SEEDS)
    rng = np.random.default_rng(1)
    layout = SpreadLayout()
    for _ in range(7):  # mid-episode
        actions = _actions(states, layout, rng)
        vec.step(actions)
        states = ref.step(actions).states
    buffer = io.BytesIO()
    torch.save(vec.state_dict(), buffer)
    buffer.seek(0)
    sd = torch.load(buffer, weights_only=True)

    clone = ConstrainedSpread(constrained=True, noise_std=0.05,
                              max_steps=MAX_STEPS).joint_vector_env(3)
    clone.load_state_dict(sd)
    for t in range(20):  # through resets: the streams went along
        actions = _actions(states, layout, rng)
        want = vec.step(actions)
        _assert_same(clone.step(actions), want, f"step {t}")
        states = want.states

    other = ConstrainedSpread(constrained=True, noise_std=0.05,
                              max_steps=MAX_STEPS).joint_vector_env(2)
    other.reset([1, 2])
    before = other.state_dict()
    with pytest.raises(ValueError, match="n_envs"):
        other.load_state_dict(sd)
    nominal = ConstrainedSpread(constrained=False, noise_std=0.05,
                                max_steps=MAX_STEPS).joint_vector_env(3)
    with pytest.raises(ValueError, match="constrained"):
        nominal.load_state_dict(sd)
    broken = dict(sd, positions=sd["positions"][:, :1])
    with pytest.raises(ValueError, match="positions"):
        clone.load_state_dict(broken)
    after = other.state_dict()  # a refused state changed nothing
    for key in ("positions", "velocities", "active", "timestep"):
        assert torch.equal(before[key], after[key])
    assert before["rngs"] == after["rngs"]


def test_vector_env_only_for_the_state_observation():
    game = ConstrainedSpread(max_steps=MAX_STEPS)
    assert JointAgentEnv(game, observation="agents").vector_env(2) is None
    assert JointAgentEnv(ConstrainedSpread(), observation="state",
                         use_state=False).vector_env(2) is None
    make = functools.partial(spread_joint_env, constrained=True, max_steps=MAX_STEPS)
    assert isinstance(vector_env_of(make, 2), SpreadVectorEnv)
    assert isinstance(vector_env_of(make, 2, batched=False), EnvList)
