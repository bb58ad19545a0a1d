"""The SAC solver's exact state: training continues after ``torch.save`` /
``torch.load(weights_only=True)`` into a fresh solver exactly as if never interrupted
(networks, optimisers, counters, replay buffer, envs mid-episode, every random stream),
with either engine (the lean loop and SB3's), also through D-ICRL's ``SACLearnerModel``;
mismatched states (another engine's included) are refused.

Tiny runs (tens of env steps) on one CPU thread: seconds in all.
"""

from __future__ import annotations

import functools
import io
import math

import numpy as np
import pytest
import torch

from dicrl_torch.algos.models import LearnerModel, SACLearnerModel
from dicrl_torch.demos.drone_demos import make_drone_demonstrations
from dicrl_torch.envs.drones import JointDroneEnv
from dicrl_torch.features.drone import (
    CellOccupancyCostBasis,
    DoorLocationRewardBasis,
    RBFCostBasis,
)
from dicrl_torch.solvers.sac import SACConstrainedSolver, SACSolution

torch.set_num_threads(1)

GAMMA = 0.95
ETA = np.array([1.0, 1.5, 0.5, 1.0, -1.0])
COST = np.random.default_rng(1).uniform(0, 1, 201)


ENGINES = ("lean", "sb3")


def make_solver(seed: int = 3, engine: str = "lean", **kwargs) -> SACConstrainedSolver:
    # 100 transitions (SB3: 50 rows per env): the buffer wraps round (full) during the
    # runs below; warm-up (random actions) ends at 80 steps, after the first save.
    args = dict(engine=engine, reward_basis=DoorLocationRewardBasis(),
                cost_basis=CellOccupancyCostBasis(), seed=seed, n_envs=2, gamma=GAMMA,
                learning_starts=80, batch_size=16, buffer_size=100, net_arch=(16, 16),
                env_factory=functools.partial(JointDroneEnv, max_steps=23),
                n_eval_episodes=2, demo_fraction=0.25)
    args.update(kwargs)
    return SACConstrainedSolver(**args)


@pytest.fixture(scope="module")
def demos():
    return make_drone_demonstrations(3, rng=np.random.default_rng(0))


def round_trip(sd: dict) -> dict:
    """Through a file, loaded without unpickling anything but plain data."""
    f = io.BytesIO()
    torch.save(sd, f)
    f.seek(0)
    return torch.load(f, weights_only=True)


def plain_types(value, path="sd") -> None:
    """Only tensors and plain python data (tuples only as torch's optimisers make them)."""
    if isinstance(value, dict):
        for k, v in value.items():
            assert isinstance(k, str | int), f"{path}: key {k!r}"
            plain_types(v, f"{path}[{k!r}]")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            plain_types(v, f"{path}[{i}]")
    else:
        assert value is None or type(value) in (torch.Tensor, int, float, bool, str), \
            f"{path}: {type(value).__name__}"


def assert_same_solution(a: SACSolution, b: SACSolution) -> None:
    for name in ("reward_sums", "cost_sums", "lengths", "reached", "violated"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(a.mu_r, b.mu_r) and torch.equal(a.mu_c, b.mu_c)
    assert a.success_rate == b.success_rate and a.timesteps == b.timesteps


# Wall-clock records of SB3's Monitors and episode-info buffer: saved and restored, but
# read by nothing in training or evaluation, and a resumed run is not at the same time.
_WALL_CLOCK = {"monitor": {"t_start", "episode_times"}, "ep_info_buffer": {"t"}}


def assert_same_state(a, b, path: str = "sd") -> None:
    """Two :meth:`SACConstrainedSolver.state_dict` values are identical: the same keys,
    tensors ``torch.equal`` (and of one dtype), plain values equal (NaN equal to NaN);
    only the wall-clock records are skipped."""
    if isinstance(a, dict):
        assert isinstance(b, dict), f"{path}: {type(b).__name__}, not a dict"
        assert a.keys() == b.keys(), f"{path}: keys {sorted(map(str, a))} != " \
                                     f"{sorted(map(str, b))}"
        clock = set().union(*(keys for where, keys in _WALL_CLOCK.items()
                              if f"[{where!r}]" in path))
        for k in a:
            if k not in clock:
                assert_same_state(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert type(a) is type(b), f"{path}: {type(a).__name__} vs {type(b).__name__}"
        assert len(a) == len(b), f"{path}: {len(a)} vs {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_state(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor), f"{path}: {type(b).__name__}"
        assert a.dtype == b.dtype and a.shape == b.shape, f"{path}: {a.dtype} {a.shape} " \
            f"vs {b.dtype} {b.shape}"
        same = torch.equal(a, b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                     and torch.equal(a.nan_to_num(), b.nan_to_num()))
        assert same, path
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), f"{path}: {a!r} vs {b!r}"
    else:
        assert type(a) is type(b) and a == b, f"{path}: {a!r} vs {b!r}"


def assert_same_solver(a: SACConstrainedSolver, b: SACConstrainedSolver) -> None:
    """Everything in the two solvers' states, and what their engines hold beside it."""
    sa, sb = a.state_dict(), b.state_dict()
    assert sa["settings"]["engine"] == sb["settings"]["engine"]
    assert_same_state(sa, sb)
    assert (a.num_timesteps, a.n_updates) == (b.num_timesteps, b.n_updates)
    pa, pb = a.policy_state(), b.policy_state()  # actor, critics and target critics
    assert pa.keys() == pb.keys()
    for key in pa:
        assert torch.equal(pa[key], pb[key]), key
    ra, rb = a.replay_buffer, b.replay_buffer
    if sa["settings"]["engine"] == "lean":
        # the labels under the current weights, recomputed at load, not saved
        assert (ra.pos, ra.size) == (rb.pos, rb.size)
        assert torch.equal(ra.rewards, rb.rewards)
        if ra._demo_torch is not None:
            assert torch.equal(ra._demo_torch["rewards"], rb._demo_torch["rewards"])
    else:
        assert (ra.pos, ra.full) == (rb.pos, rb.full)
        assert np.array_equal(a.engine.model._last_obs, b.engine.model._last_obs)


def buffer_full(solver: SACConstrainedSolver) -> bool:
    buf = solver.replay_buffer
    return buf.size == buf.capacity if solver.engine.name == "lean" else buf.full


@pytest.mark.parametrize("engine", ENGINES)
def test_training_continues_exactly_from_a_saved_state(demos, engine):
    # Uninterrupted: three solves (new weights each time) on one solver.
    ref = make_solver(engine=engine)
    ref.set_demonstrations(demos)
    weights = [(ETA, COST), (ETA * 0.5, COST * 2), (ETA * 2, COST * 0.5)]
    steps = (60, 60, 60)  # 30 steps per env each: episodes of 23 are cut mid-way
    expected = [ref.solve(eta, wc, t) for (eta, wc), t in zip(weights, steps, strict=True)]
    assert buffer_full(ref) and ref.n_updates > 0

    # Interrupted after every solve: saved, loaded into a fresh solver built with the
    # same arguments (no demonstrations set: they are part of the state), continued.
    solver = make_solver(engine=engine)
    solver.set_demonstrations(demos)
    got = solver.solve(*weights[0], steps[0])
    for k in (1, 2):
        sd = solver.state_dict()
        plain_types(sd)
        solver.close()
        solver = make_solver(engine=engine)
        solver.load_state_dict(round_trip(sd))
        assert_same_state(solver.state_dict(), sd)  # loaded is what was saved
        got_k = solver.solve(*weights[k], steps[k])
        assert_same_solution(got_k, expected[k])
    assert_same_solution(got, expected[0])
    assert_same_solver(solver, ref)
    # ... and it goes on identically: more training, evaluation, the likelihood
    assert_same_solution(solver.solve(ETA, COST, 30), ref.solve(ETA, COST, 30))
    assert solver.log_likelihood(demos) == ref.log_likelihood(demos)

    # Without the state a fresh solver does not reproduce the run (the test can fail).
    fresh = make_solver(engine=engine)
    fresh.set_demonstrations(demos)
    other = fresh.solve(*weights[1], steps[1])
    assert not torch.equal(other.cost_sums, expected[1].cost_sums) \
        or not torch.equal(other.reward_sums, expected[1].reward_sums)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("kwargs", [dict(per_agent_critics=True, scale_observations=True)])
def test_exact_state_with_per_agent_critics_and_a_clone(demos, kwargs, engine):
    # A clone (its own seed and streams, not yet drawn from) saved into a fresh solver
    # built with the ORIGINAL's arguments: the state carries the clone's seed.
    kwargs = dict(kwargs, engine=engine)
    base = make_solver(**kwargs)
    base.solve(ETA, COST, 40)
    ref = base.clone(11)
    ref.set_demonstrations(demos)
    solver = make_solver(**kwargs)
    solver.load_state_dict(round_trip(ref.state_dict()))
    assert solver.seed == 11
    assert_same_solution(solver.solve(ETA, COST, 70), ref.solve(ETA, COST, 70))
    assert_same_solver(solver, ref)
    # the clone's seed also decides its own later clones and restarts
    a = solver.solve_keeping_best(ETA, COST, 20, checks=2, restarts=2)
    b = ref.solve_keeping_best(ETA, COST, 20, checks=2, restarts=2)
    assert_same_solution(a, b)
    assert solver.last_checks == ref.last_checks


def test_learner_model_state_covers_every_learners_solver(demos):
    def model(base_seed: int) -> SACLearnerModel:
        base = make_solver(base_seed)
        solvers = [base.clone(20), base.clone(21)]
        for s in solvers:
            s.set_demonstrations(demos)
        return SACLearnerModel(solvers=solvers, timesteps=50, n_eval_episodes=2)

    eta, wc = torch.as_tensor(ETA), torch.as_tensor(COST)
    ref = model(3)
    assert isinstance(ref, LearnerModel) and ref.stateful
    for i in (0, 1):
        ref.solve(i, eta, wc)
    sd = round_trip(ref.state_dict())
    plain_types(sd)
    # a fresh model whose solvers were built (and seeded) differently: all comes from sd
    back = model(5)
    back.load_state_dict(sd)
    for i in (0, 1):
        assert_same_solution(back.solve(i, eta * 0.5, wc), ref.solve(i, eta * 0.5, wc))
        assert back.log_likelihood(i, eta, wc, demos) == ref.log_likelihood(i, eta, wc, demos)
        assert_same_solver(back.inner_solver(i), ref.inner_solver(i))
    with pytest.raises(ValueError, match="holds 2 solver states, the model 1"):
        SACLearnerModel(solvers=[make_solver()], timesteps=1).load_state_dict(sd)


# What each engine names first when the state's networks have other shapes: the lean
# engine keeps net_arch among its settings, SB3's finds it in its network tensors.
_OTHER_NETWORK = {
    "lean": r"net_arch: state \[16, 16\], this solver \[8, 8\]",
    "sb3": r"SAC network tensor 'actor\.latent_pi\.0\.weight'.*\[16, 20\].*\[8, 20\]"}
# buffer_size counts transitions with the lean engine, rows per env with SB3's
_BUFFER_SIZE = {"lean": "buffer_size: state 100, this solver 200",
                "sb3": "buffer_size: state 50, this solver 100"}


def assert_refused_and_unchanged(solver: SACConstrainedSolver, sd: dict, match: str) -> None:
    """Loading ``sd`` raises a ValueError matching ``match`` and changes nothing."""
    before = round_trip(solver.state_dict())  # a copy: nothing shared with the solver
    with pytest.raises(ValueError, match=match):
        solver.load_state_dict(sd)
    assert_same_state(solver.state_dict(), before)


@pytest.mark.parametrize("engine", ENGINES)
def test_mismatched_states_are_refused_and_change_nothing(demos, engine):
    solver = make_solver(engine=engine)
    solver.set_demonstrations(demos)
    solver.solve(ETA, COST, 30)
    sd = round_trip(solver.state_dict())

    other = make_solver(engine=engine, net_arch=(8, 8))
    assert_refused_and_unchanged(other, sd, _OTHER_NETWORK[engine])
    assert other.num_timesteps == 0 and other.replay_buffer.pos == 0
    # the other engine's state, both ways (a solver that trained already: nothing moves)
    foreign = make_solver(engine="sb3" if engine == "lean" else "lean")
    foreign.solve(ETA * 2, COST, 20)
    assert_refused_and_unchanged(
        foreign, sd, f"engine: state '{engine}', this solver '{foreign.engine.name}'")
    assert foreign.num_timesteps == 20

    with pytest.raises(ValueError, match="cost_features: state 201, this solver"):
        make_solver(engine=engine, cost_basis=RBFCostBasis(n_per_axis=4)).load_state_dict(sd)
    with pytest.raises(ValueError, match="n_envs: state 2, this solver 1"):
        make_solver(engine=engine, n_envs=1).load_state_dict(sd)
    with pytest.raises(ValueError, match=_BUFFER_SIZE[engine]):
        make_solver(engine=engine, buffer_size=200).load_state_dict(sd)
    with pytest.raises(ValueError, match="gamma: state 0.95, this solver 0.9"):
        make_solver(engine=engine, gamma=0.9).load_state_dict(sd)
    # a damaged buffer field is named (and a solver refusing it stays as it was)
    buffer = "replay" if engine == "lean" else "replay_buffer"
    bad = round_trip(solver.state_dict())
    bad["engine"][buffer]["stored"]["cost_features"] = \
        bad["engine"][buffer]["stored"]["cost_features"][..., :7]
    assert_refused_and_unchanged(make_solver(engine=engine), bad,
                                 "replay buffer field 'cost_features'.*201")
    bad = round_trip(solver.state_dict())
    bad["engine"][buffer]["demo"]["phi_c"] = bad["engine"][buffer]["demo"]["phi_c"][:, :7]
    assert_refused_and_unchanged(make_solver(engine=engine), bad,
                                 "replay buffer demonstrations 'phi_c'.*201")
    bad = round_trip(solver.state_dict())
    del bad["engine"]["envs"]
    assert_refused_and_unchanged(make_solver(engine=engine), bad, "Malformed")
    with pytest.raises(ValueError, match="Not a SACConstrainedSolver state"):
        make_solver(engine=engine).load_state_dict({"policy": {}})
