"""The SAC solver's exact state: training continues after ``torch.save`` /
``torch.load(weights_only=True)`` into a fresh solver exactly as if never interrupted
(networks, optimisers, SB3 counters, replay buffer, envs mid-episode, every random
stream), also through D-ICRL's ``SACLearnerModel``; mismatched states are refused.

Tiny runs (tens of env steps) on one CPU thread: seconds in all.
"""

from __future__ import annotations

import functools
import io

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


def make_solver(seed: int = 3, **kwargs) -> SACConstrainedSolver:
    # 50 rows per env: the buffer wraps round (full) during the runs below; warm-up
    # (random actions) ends at 80 steps, after the first save.
    args = dict(reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(),
                seed=seed, n_envs=2, gamma=GAMMA, learning_starts=80, batch_size=16,
                buffer_size=100, net_arch=(16, 16),
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


def assert_same_solver(a: SACConstrainedSolver, b: SACConstrainedSolver) -> None:
    pa, pb = a.model.policy.state_dict(), b.model.policy.state_dict()
    assert pa.keys() == pb.keys()
    for key in pa:  # actor, critics and target critics
        assert torch.equal(pa[key], pb[key]), key
    for opt in ("actor", "critic"):
        sa = getattr(a.model, opt).optimizer.state_dict()["state"]
        sb = getattr(b.model, opt).optimizer.state_dict()["state"]
        for i in sa:
            for k in sa[i]:
                assert torch.equal(sa[i][k], sb[i][k]), (opt, i, k)
    ra, rb = a.replay_buffer, b.replay_buffer
    assert (ra.pos, ra.full) == (rb.pos, rb.full)
    for name in ra._STORED:
        assert np.array_equal(getattr(ra, name), getattr(rb, name)), name
    for attr in ("num_timesteps", "_n_updates", "_episode_num"):
        assert getattr(a.model, attr) == getattr(b.model, attr), attr
    assert np.array_equal(a.model._last_obs, b.model._last_obs)


def test_training_continues_exactly_from_a_saved_state(demos):
    # Uninterrupted: three solves (new weights each time) on one solver.
    ref = make_solver()
    ref.set_demonstrations(demos)
    weights = [(ETA, COST), (ETA * 0.5, COST * 2), (ETA * 2, COST * 0.5)]
    steps = (60, 60, 60)  # 30 steps per env each: episodes of 23 are cut mid-way
    expected = [ref.solve(eta, wc, t) for (eta, wc), t in zip(weights, steps, strict=True)]
    assert ref.replay_buffer.full and ref.model._n_updates > 0

    # Interrupted after every solve: saved, loaded into a fresh solver built with the
    # same arguments (no demonstrations set: they are part of the state), continued.
    solver = make_solver()
    solver.set_demonstrations(demos)
    got = solver.solve(*weights[0], steps[0])
    for k in (1, 2):
        sd = solver.state_dict()
        plain_types(sd)
        solver.close()
        solver = make_solver()
        solver.load_state_dict(round_trip(sd))
        got_k = solver.solve(*weights[k], steps[k])
        assert_same_solution(got_k, expected[k])
    assert_same_solution(got, expected[0])
    assert_same_solver(solver, ref)
    # ... and it goes on identically: more training, evaluation, the likelihood
    assert_same_solution(solver.solve(ETA, COST, 30), ref.solve(ETA, COST, 30))
    assert solver.log_likelihood(demos) == ref.log_likelihood(demos)

    # Without the state a fresh solver does not reproduce the run (the test can fail).
    fresh = make_solver()
    fresh.set_demonstrations(demos)
    other = fresh.solve(*weights[1], steps[1])
    assert not torch.equal(other.cost_sums, expected[1].cost_sums) \
        or not torch.equal(other.reward_sums, expected[1].reward_sums)


@pytest.mark.parametrize("kwargs", [dict(per_agent_critics=True, scale_observations=True)])
def test_exact_state_with_per_agent_critics_and_a_clone(demos, kwargs):
    # A clone (its own seed and streams, not yet drawn from) saved into a fresh solver
    # built with the ORIGINAL's arguments: the state carries the clone's seed.
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


def test_mismatched_states_are_refused_and_change_nothing():
    solver = make_solver()
    solver.solve(ETA, COST, 30)
    sd = round_trip(solver.state_dict())

    other = make_solver(net_arch=(8, 8))
    before = {k: v.clone() for k, v in other.model.policy.state_dict().items()}
    with pytest.raises(ValueError, match=r"SAC network tensor 'actor\.latent_pi\.0\.weight'.*"
                                         r"\[16, 20\].*\[8, 20\]"):
        other.load_state_dict(sd)
    for key, value in other.model.policy.state_dict().items():
        assert torch.equal(value, before[key]), key
    assert other.num_timesteps == 0 and other.replay_buffer.pos == 0

    with pytest.raises(ValueError, match="cost_features: state 201, this solver"):
        make_solver(cost_basis=RBFCostBasis(n_per_axis=4)).load_state_dict(sd)
    with pytest.raises(ValueError, match="n_envs: state 2, this solver 1"):
        make_solver(n_envs=1).load_state_dict(sd)
    with pytest.raises(ValueError, match="buffer_size: state 50, this solver 100"):
        make_solver(buffer_size=200).load_state_dict(sd)
    with pytest.raises(ValueError, match="gamma: state 0.95, this solver 0.9"):
        make_solver(gamma=0.9).load_state_dict(sd)
    # a damaged buffer field is named
    bad = round_trip(solver.state_dict())
    bad["replay_buffer"]["stored"]["cost_features"] = \
        bad["replay_buffer"]["stored"]["cost_features"][:, :, :7]
    with pytest.raises(ValueError, match="replay buffer field 'cost_features'.*201"):
        make_solver().load_state_dict(bad)
    bad = round_trip(solver.state_dict())
    del bad["envs"]
    with pytest.raises(ValueError, match="Malformed"):
        make_solver().load_state_dict(bad)
    with pytest.raises(ValueError, match="Not a SACConstrainedSolver state"):
        make_solver().load_state_dict({"policy": {}})
