"""The drone game's batched joint env (:class:`DroneVectorEnv`) against its reference, an
:class:`EnvList` of :class:`JointDroneEnv` s: the same transitions bit for bit, its exact
state and its per-slot random streams."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from dicrl_torch.envs.drones import DroneDynamics, DroneVectorEnv, JointDroneEnv
from dicrl_torch.envs.vector import VectorStep
from dicrl_torch.solvers.sac.env_list import EnvList, vector_env_of
from dicrl_torch.solvers.sac.randomness import generator_state_dict, restore_generator

SEEDS = [5, 6, 7]
FIELDS = ("obs", "final_obs", "states", "terminated", "truncated", "reached", "violated")
DTYPES = {"obs": np.float32, "final_obs": np.float32, "states": np.float64,
          "terminated": np.bool_, "truncated": np.bool_, "reached": np.bool_,
          "violated": np.bool_}


def policy(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``[3, 4]`` actions for 3 slots, many outside ``[-1, 1]`` (the clip is tested):
    slot 0 drives both drones into the obstacle (and each other), slot 1 flies them
    round it to their doors, slot 2 flies at random (its episodes run to the limit)."""
    pos = obs.reshape(3, 2, 10)[:, :, :2].astype(np.float64)  # [slot, drone, xy]
    target = np.empty_like(pos)
    target[0] = (5.0, 5.5)
    target[1, 0] = (8.75, 3.0) if pos[1, 0, 0] < 8.3 else (8.75, 10.0)
    target[1, 1] = (1.25, 1.0) if pos[1, 1, 0] > 1.7 else (1.25, 10.0)
    a = 2.0 * (target - pos) + rng.normal(0.0, 0.3, pos.shape)
    a[2] = rng.uniform(-1.5, 1.5, (2, 2))
    return a.reshape(3, 4).astype(np.float32)


def settings(constrained: bool, command_set: str) -> dict:
    """Fast box drones with a 20-step limit (truncations, violations) or the disc's
    drones with time to reach their doors."""
    if command_set == "box":
        return {"constrained": constrained, "max_steps": 20,
                "dynamics": DroneDynamics(max_speed=3.0)}
    return {"constrained": constrained, "max_steps": 120,
            "dynamics": DroneDynamics(command_set="disc", max_speed=1.5)}


def pair(n: int = 3, **kwargs) -> tuple[DroneVectorEnv, EnvList]:
    vec = JointDroneEnv(**kwargs).vector_env(n)
    return vec, EnvList(lambda: JointDroneEnv(**kwargs), n)


def assert_same_step(got: VectorStep, want: VectorStep, where: str) -> None:
    # Exact: the batch runs the reference's elementwise float64 operations on the same
    # operands (the only reductions are sums of 2 numbers), so no rounding differs.
    for f in FIELDS:
        g, w = getattr(got, f), getattr(want, f)
        assert g.dtype == DTYPES[f] and g.shape == w.shape, (where, f, g.dtype, g.shape)
        assert np.array_equal(g, w), f"{where}: {f} differs\n{g}\n{w}"


@pytest.mark.parametrize("command_set", ["box", "disc"])
@pytest.mark.parametrize("constrained", [True, False])
def test_steps_equal_the_reference_env_list(constrained, command_set):
    kw = settings(constrained, command_set)
    vec, ref = pair(**kw)
    obs, states = vec.reset(SEEDS)
    ref_obs, ref_states = ref.reset(SEEDS)
    assert obs.dtype == np.float32 and states.dtype == np.float64
    assert np.array_equal(obs, ref_obs) and np.array_equal(states, ref_states)
    rng = np.random.default_rng(0)
    totals = dict.fromkeys(("terminated", "truncated", "reached", "violated", "clipped"), 0)
    for t in range(100 if command_set == "box" else 300):
        actions = policy(obs, rng)
        totals["clipped"] += int((np.abs(actions) > 1).sum())
        got, want = vec.step(actions), ref.step(actions)
        assert_same_step(got, want, f"step {t}")
        for key in ("terminated", "truncated", "reached", "violated"):
            totals[key] += int(getattr(got, key).sum())
        obs = got.obs
    # Not vacuous: episodes ended both ways and were reset, the constraints were hit,
    # commands were clipped, and (given time) drones reached their doors.
    assert totals["truncated"] and totals["violated"] and totals["clipped"], totals
    assert totals["terminated"] or not constrained, totals
    assert totals["reached"] or command_set == "box", totals


def test_a_done_drone_reports_no_flags():
    # A drone frozen in the obstacle (true game) stays inside it, but only the step it
    # froze in reports the violation: the reference gives flags to live agents only.
    vec, ref = pair(**settings(True, "box"))
    vec.reset(SEEDS)
    ref.reset(SEEDS)
    env = ref.envs[0]
    env.arena._state[0, :2] = (4.5, 4.9)  # drone 0 just below the obstacle, slot 0 only
    vec._states[0, 0, :2] = (4.5, 4.9)
    up = np.zeros((3, 4), dtype=np.float32)
    up[:, 1] = 1.0
    flags = []
    for t in range(4):
        got, want = vec.step(up), ref.step(up)
        assert_same_step(got, want, f"step {t}")
        flags.append(bool(got.violated[0, 0]))
        assert not got.done[0]
    assert flags.count(True) == 1 and not env.arena.active[0], flags


def test_an_episode_ending_at_the_limit_is_terminated_not_truncated():
    vec, ref = pair(**settings(True, "box"))
    vec.reset(SEEDS)
    ref.reset(SEEDS)
    # Slot 0's drones inside the obstacle, 1 m apart, one step before the limit: both
    # violate and freeze in the last step.
    inside = np.array([[4.5, 5.5, 0.0, 0.0], [5.5, 5.5, 0.0, 0.0]])
    arena = ref.envs[0].arena
    arena._state[:] = inside
    arena.timestep = vec._timestep[0] = arena.max_steps - 1
    vec._states[0] = inside
    actions = np.zeros((3, 4), dtype=np.float32)
    got, want = vec.step(actions), ref.step(actions)
    assert_same_step(got, want, "last step")
    assert got.terminated[0] and not got.truncated[0] and got.violated[0].all()


def test_vector_env_takes_the_joint_envs_settings():
    dyn = DroneDynamics(command_set="disc", max_speed=1.5)
    env = JointDroneEnv(constrained=False, max_steps=33, dynamics=dyn, proximity_radius=0.7)
    vec = env.vector_env(4)
    assert isinstance(vec, DroneVectorEnv) and vec.n_envs == 4
    assert (vec.constrained, vec.max_steps, vec.dynamics, vec.proximity_radius) == \
        (False, 33, dyn, 0.7)
    assert vec.n_agents == env.n_agents and vec.state_shape == env.state_shape
    assert vec.observation_space == env.observation_space
    assert vec.action_space == env.action_space
    assert isinstance(vector_env_of(lambda: JointDroneEnv(max_steps=5), 2), DroneVectorEnv)
    assert isinstance(vector_env_of(JointDroneEnv, 2, batched=False), EnvList)


@pytest.mark.parametrize("n_envs", [0, -1, 2.0, True, "3", None])
def test_n_envs_must_be_a_positive_int(n_envs):
    with pytest.raises(ValueError, match="n_envs must be a positive int"):
        DroneVectorEnv(n_envs)


def test_bad_calls_are_refused():
    vec = DroneVectorEnv(3, max_steps=20)
    with pytest.raises(RuntimeError, match="before reset"):
        vec.step(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="seeds must be 3 ints"):
        vec.reset([1, 2])
    vec.reset(SEEDS)
    for bad in (np.zeros((2, 4)), np.zeros((3, 2, 2)), np.full((3, 4), np.nan), "left"):
        with pytest.raises(ValueError, match=r"actions must be a finite \[3, 4\] array"):
            vec.step(bad)
    with pytest.raises(ValueError, match="slot must be an int"):
        vec.set_rng(3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="max_steps"):
        DroneVectorEnv(2, max_steps=0)


def roundtrip(sd: dict) -> dict:
    buf = io.BytesIO()
    torch.save(sd, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


def test_state_dict_roundtrip_continues_identically():
    kw = settings(True, "box")
    vec, _ = pair(**kw)
    obs, _ = vec.reset(SEEDS)
    rng = np.random.default_rng(1)
    for _ in range(13):  # mid-episode, some slots past a reset
        obs = vec.step(policy(obs, rng)).obs
    sd = roundtrip(vec.state_dict())
    copy = DroneVectorEnv(3, **kw)
    copy.load_state_dict(sd)
    # The solver's generator helpers read the same format.
    assert restore_generator(None, sd["rngs"][0]).bit_generator.state == \
        vec._rngs[0].bit_generator.state
    assert sd["rngs"][1] == generator_state_dict(vec._rngs[1])
    for t in range(40):
        actions = policy(obs, rng)
        got, want = copy.step(actions), vec.step(actions)
        assert_same_step(got, want, f"step {t} after loading")
        obs = want.obs


def test_load_state_dict_refuses_a_wrong_state_and_changes_nothing():
    vec = DroneVectorEnv(2, max_steps=20)
    vec.reset([1, 2])
    before = vec.state_dict()
    other = DroneVectorEnv(3, max_steps=20)
    other.reset(SEEDS)
    with pytest.raises(ValueError, match="holds 3 slots, this env 2"):
        vec.load_state_dict(roundtrip(other.state_dict()))
    bad = dict(before, states=before["states"].float())
    with pytest.raises(ValueError, match="'states' is shape \\[2, 2, 4\\] torch.float32"):
        vec.load_state_dict(bad)
    bad = dict(before, rngs=[before["rngs"][0], {"bit_generator": "NoSuchBitGen"}])
    with pytest.raises(ValueError, match="slot 1's random stream"):
        vec.load_state_dict(bad)
    with pytest.raises(ValueError, match="not a drone arena's batched state"):
        vec.load_state_dict({"n_envs": 2, "envs": []})  # an EnvList's
    after = vec.state_dict()
    assert after.keys() == before.keys() and after["rngs"] == before["rngs"]
    for key in ("states", "active", "timestep"):
        assert torch.equal(after[key], before[key])


def test_set_rng_changes_only_that_slots_future_noise():
    kw = settings(False, "box")
    vec, ref = pair(**kw)
    untouched, _ = pair(**kw)
    for env in (vec, ref, untouched):
        env.reset(SEEDS)
    actions = np.full((3, 4), 0.3, dtype=np.float32)
    for _ in range(3):
        first = vec.step(actions)
        returned = {f: getattr(first, f).copy() for f in FIELDS}
        ref.step(actions)
        untouched.step(actions)
    vec.set_rng(1, np.random.default_rng(99))
    ref.set_rng(1, np.random.default_rng(99))
    differs = False
    for t in range(30):  # past the 20-step limit: the resets draw from the new stream too
        got, want, plain = vec.step(actions), ref.step(actions), untouched.step(actions)
        assert_same_step(got, want, f"step {t} after set_rng")
        for f in FIELDS:
            assert np.array_equal(getattr(got, f)[[0, 2]], getattr(plain, f)[[0, 2]])
        differs |= not np.array_equal(got.states[1], plain.states[1])
    assert differs
    for f in FIELDS:  # what a step returned is its own: later steps do not rewrite it
        assert np.array_equal(getattr(first, f), returned[f])
