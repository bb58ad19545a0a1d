"""torch.distributed backend (gloo, one process per learner): bit-identical numbers to
the simulated backend, identical trainer trajectories, fail-fast on dead, silent or
missing learners, configuration agreement and the privacy audit on every rank.

The learner bodies are module-level functions: spawned processes import this module
to find them, and rebuild their inputs from a seed instead of receiving tensors.
"""

from __future__ import annotations

import json
import os
import time

import pytest
import tiny_dicrl
import torch
import torch.distributed as dist

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.comm import (
    ALLOWED_FIELDS,
    CompleteSchedule,
    MessageRecord,
    RingSchedule,
    SimulatedCommunicator,
    TimeVaryingSchedule,
)
from dicrl_torch.comm.compression import Compression
from dicrl_torch.comm.distributed import (
    ConfigMismatchError,
    DistributedCommunicator,
    LearnerProcessError,
    PeerFailureError,
    free_port,
    shard_for_rank,
    spawn_learners,
)

pytestmark = pytest.mark.skipif(not (dist.is_available() and dist.is_gloo_available()),
                                reason="torch.distributed with gloo is not available")

SPLIT = tiny_dicrl.SPLIT
build_tiny = tiny_dicrl.build_tiny
COMM_TIMEOUT_S = 30.0  # generous: 3-4 processes start on a 2-core machine


# ---------------------------------------------------------------------- the tiny instance
def make_trainer(tiny, shards, communicator, **trainer_options) -> DICRL:
    return tiny_dicrl.make_trainer(tiny, shards=shards, communicator=communicator,
                                   **trainer_options)


TRAINER_OPTIONS = ("inner_method",)


def split_options(options: dict) -> tuple[dict, dict]:
    """(communicator keywords, trainer keywords) from one option dict of plain values."""
    trainer = {k: v for k, v in options.items() if k in TRAINER_OPTIONS}
    return comm_options({k: v for k, v in options.items() if k not in trainer}), trainer


def random_inputs(seed: int, n: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Values ``[n, ...]`` (float64 and float32) and mixing matrices ``[n, n]``."""
    g = torch.Generator().manual_seed(seed)
    xs = [torch.randn(n, 7, generator=g, dtype=torch.float64),
          torch.randn(n, 3, 4, generator=g, dtype=torch.float64) * 1e3,
          torch.randn(n, 5, generator=g, dtype=torch.float32)]
    raw = torch.rand(n, n, generator=g, dtype=torch.float64)
    Ws = [CompleteSchedule(n_learners=n)(0), RingSchedule(n_learners=n)(0),
          TimeVaryingSchedule(n_learners=n, period=2)(1),
          raw / raw.sum(1, keepdim=True),
          torch.randn(n, n, generator=g, dtype=torch.float64)]  # any W: mix is linear
    return xs, Ws


def _comm(rank, world_size, init_method, **kw) -> DistributedCommunicator:
    kw.setdefault("timeout_s", COMM_TIMEOUT_S)
    return DistributedCommunicator(init_method=init_method, rank=rank, world_size=world_size,
                                   **kw)


# ---------------------------------------------------------------------- learner bodies
def _collectives_body(rank, world_size, init_method, seed):
    xs, Ws = random_inputs(seed, world_size)
    with _comm(rank, world_size, init_method) as comm:
        assert comm.local_ids == [rank] and comm.n_learners == world_size
        comm.check_same_config("same configuration")
        gathered = [comm.all_gather(x[rank:rank + 1], "eta") for x in xs]
        mixed = [comm.mix(x[rank:rank + 1], W, "cost_weights") for x in xs for W in Ws]
        # control values of different lengths per rank (checkpointed iterations)
        control = comm.gather_control({"rank": rank, "saved": list(range(rank))},
                                      "checkpointed_iterations")
        comm.barrier()
        # the last rank was started with another configuration
        try:
            comm.check_same_config("alpha_bar=0.05" if rank == world_size - 1
                                   else "alpha_bar=0.02")
            mismatch = None
        except ConfigMismatchError as e:
            mismatch = str(e)
    return gathered, mixed, mismatch, control


def comm_options(options: dict) -> dict:
    """Communicator keywords from plain values (what a spawned body receives)."""
    options = dict(options)
    if "bits" in options:
        options["compression"] = Compression(bits=options.pop("bits"))
    return options


def _trainer_body(rank, world_size, init_method, outer_iterations, options=None):
    tiny = build_tiny()
    comm_kw, trainer_kw = split_options(options or {})
    with _comm(rank, world_size, init_method, record=True, **comm_kw) as comm:
        comm.check_same_config(f"tiny split={SPLIT} K=3 alpha_bar=0.02 rho=10")
        t = make_trainer(tiny, [shard_for_rank(tiny[3], rank)], comm, **trainer_kw)
        t.train(outer_iterations)
        st = t.state
        return {"cost_weights": st.cost_weights[0], "eta_bar": st.eta_bar[0],
                "tracker": st.tracker[0], "eta": st.eta[:, 0],
                "inner_processes": [h["inner_processes"] for h in t.history],
                # plain tuples: results come back through torch.load(weights_only=True)
                "messages": [(m.field, m.shape, m.sender) for m in comm.messages],
                "traffic": json.dumps(comm.traffic.report(rank)),
                "dims": (t.learner_model.cost_dim, t.learner_model.reward_dim + 1)}


def _dies_body(rank, world_size, init_method):
    comm = _comm(rank, world_size, init_method)
    if rank == 2:
        os._exit(1)  # dies after joining, before the first collective
    comm.all_gather(torch.zeros(1, 3, dtype=torch.float64), "eta")


def _silent_body(rank, world_size, init_method, timeout_s):
    comm = _comm(rank, world_size, init_method, timeout_s=timeout_s)
    if rank == 2:
        time.sleep(600)  # alive but never takes part; the helper terminates it
    t0 = time.monotonic()
    try:
        comm.mix(torch.zeros(1, 3, dtype=torch.float64), torch.eye(world_size), "tracker")
    except PeerFailureError:
        print(f"rank {rank}: PeerFailureError after {time.monotonic() - t0:.2f} s", flush=True)
        raise


def _late_body(rank, world_size, init_method, timeout_s, late_s, wait_s, late_rank=1):
    """Rank ``late_rank`` reaches the barrier ``late_s`` after the others; the barrier
    waits ``wait_s`` (None: the communicator's ``timeout_s``)."""
    with _comm(rank, world_size, init_method, timeout_s=timeout_s) as comm:
        if rank == late_rank:
            time.sleep(late_s)
        comm.barrier(timeout_s=wait_s)
    return rank


def _never_joined_body(rank, world_size, init_method, claimed_world_size, timeout_s):
    t0 = time.monotonic()
    try:
        _comm(rank, claimed_world_size, init_method, timeout_s=timeout_s)
    except PeerFailureError as e:
        return str(e), time.monotonic() - t0
    return None, time.monotonic() - t0


def _raise_or_sleep_body(rank, world_size, init_method):
    if rank == 0:
        raise ValueError("bad input on rank 0")
    time.sleep(600)


def _sleep_body(rank, world_size, init_method):
    time.sleep(600)


# ---------------------------------------------------------------------- numbers
N_COLLECTIVES, SEED = 4, 123


@pytest.fixture(scope="module")
def collectives_run():
    """Per-rank results of :func:`_collectives_body` in 4 processes."""
    return spawn_learners(_collectives_body, N_COLLECTIVES, args=(SEED,), timeout_s=120)


def test_all_gather_and_mix_are_bitwise_equal_to_simulated(collectives_run):
    xs, Ws = random_inputs(SEED, N_COLLECTIVES)
    sim = SimulatedCommunicator(N_COLLECTIVES)
    for rank, (gathered, mixed, _, _) in enumerate(collectives_run):
        for x, g in zip(xs, gathered, strict=True):
            assert g.dtype == x.dtype and torch.equal(g, sim.all_gather(x, "eta"))
        expected = [sim.mix(x, W, "cost_weights")[rank:rank + 1] for x in xs for W in Ws]
        for e, m in zip(expected, mixed, strict=True):
            assert m.dtype == e.dtype and torch.equal(m, e)


def test_control_values_reach_every_rank_in_rank_order(collectives_run):
    every = [{"rank": r, "saved": list(range(r))} for r in range(N_COLLECTIVES)]
    for _, _, _, control in collectives_run:
        assert control == every


def test_control_values_are_audited_and_only_known_fields_are_sent():
    from dicrl_torch.comm.communicator import CONTROL_FIELDS

    sim = SimulatedCommunicator(2, record=True)
    assert sim.gather_control(["/runs/x", "id"], "run_directory") == [["/runs/x", "id"]] * 2
    # each learner's value, to the other: the audit has one record per sender
    assert [(m.field, m.sender, m.recipients) for m in sim.messages] == [
        ("run_directory", 0, (1,)), ("run_directory", 1, (0,))]
    assert set(CONTROL_FIELDS).isdisjoint(ALLOWED_FIELDS)  # never learner data
    with pytest.raises(ValueError, match="not one a run exchanges"):
        sim.gather_control([1.0, 2.0], "demonstrations")


def test_different_configurations_raise_on_every_rank(collectives_run):
    for _, _, mismatch, _ in collectives_run:
        assert mismatch is not None
        assert "ranks [3] differ from ranks [0, 1, 2]" in mismatch


@pytest.fixture(scope="module")
def trainer_runs():
    """(simulated trainer, per-rank results of the 3-process run), 2 outer iterations."""
    tiny = build_tiny()
    sim = make_trainer(tiny, tiny[3], SimulatedCommunicator(len(SPLIT), record=True))
    sim.train(2)
    return sim, spawn_learners(_trainer_body, len(SPLIT), args=(2,), timeout_s=180)


def test_trainer_trajectories_are_identical(trainer_runs):
    sim, runs = trainer_runs
    for rank, r in enumerate(runs):
        for key in ("cost_weights", "eta_bar", "tracker"):
            expected = getattr(sim.state, key)[rank]
            diff = (r[key] - expected).abs().max().item()
            assert diff <= 1e-9, f"rank {rank} {key}: max |diff| {diff:.3g}"
            assert torch.equal(r[key], expected), f"rank {rank} {key}: not bitwise equal"
        assert torch.equal(r["eta"], sim.state.eta[:, rank])
        assert r["inner_processes"] == [h["inner_processes"] for h in sim.history]


# int8 messages of every mixed field and no redundant ω_c gather (the point-to-point
# transport of compressed messages); inner links that fail (realised alike everywhere);
# the tracking inner process (two exchanges a step over the period-2 graph, a tracker)
OPTIONS = {"int8": {"bits": 8, "skip_redundant_rounds": True},
           "failing_links": {"link_failure": 0.3, "link_seed": 1},
           "tracking": {"inner_method": "tracking"}}


# Failing links on spawned processes are the slow suite's: int8 exercises the same
# exchange path, and failing links are checked against their own truth in test_comm_traffic.
@pytest.fixture(scope="module", params=[
    "int8", "tracking", pytest.param("failing_links", marks=pytest.mark.slow)])
def option_runs(request):
    tiny = build_tiny()
    options = OPTIONS[request.param]
    comm_kw, trainer_kw = split_options(options)
    sim = make_trainer(tiny, tiny[3], SimulatedCommunicator(
        len(SPLIT), record=True, **comm_kw), **trainer_kw)
    sim.train(3)
    return sim, spawn_learners(_trainer_body, len(SPLIT), args=(3, options), timeout_s=180)


def check_traffic(sim, runs) -> None:
    """The bytes a rank counts are those its collectives and point-to-point sends moved,
    and equal the simulated run's count for that learner, phase by phase; but for the
    control phase: learner processes check that they share a configuration, which one
    process need not (32 int64 to each other learner)."""
    for rank, r in enumerate(runs):
        got, want = json.loads(r["traffic"]), sim.comm.traffic.report(rank)
        for direction in ("sent", "received"):
            assert got[direction].pop("control") == {
                "messages": len(SPLIT) - 1, "scalars": 0, "bytes": (len(SPLIT) - 1) * 256}
            assert want[direction].pop("control")["bytes"] == 0
        assert got == want
        assert sim.comm.traffic.bytes_sent(rank) > 0


def test_traffic_counted_on_each_rank_equals_the_simulated_count(trainer_runs):
    check_traffic(*trainer_runs)


def test_traffic_with_each_option_equals_the_simulated_count(option_runs):
    check_traffic(*option_runs)


def test_trajectories_with_each_option_are_identical(option_runs):
    sim, runs = option_runs
    for rank, r in enumerate(runs):
        for key in ("cost_weights", "eta_bar", "tracker"):
            assert torch.equal(r[key], getattr(sim.state, key)[rank]), (rank, key)


def test_privacy_audit_on_every_rank(trainer_runs):
    sim, runs = trainer_runs
    d, p = runs[0]["dims"]
    sizes = {"eta": (p,), "cost_weights": (d,), "tracker": (d,)}
    for rank, r in enumerate(runs):
        msgs = r["messages"]  # (field, shape, sender)
        # Algorithm 2 (the default inner method) sends no inner gradient tracker.
        assert {field for field, _, _ in msgs} == {"eta", "cost_weights", "tracker"}
        assert set(sizes) <= set(ALLOWED_FIELDS)
        for field, shape, sender in msgs:
            assert field in ALLOWED_FIELDS and tuple(shape) == sizes[field]
            assert sender == rank
        # the same messages, in the same order, as that learner in the simulated run
        own = [(m.field, m.shape) for m in sim.comm.messages if m.sender == rank]
        assert [(field, tuple(shape)) for field, shape, _ in msgs] == own


# ---------------------------------------------------------------------- faults
def test_a_learner_that_dies_fails_fast():
    t0 = time.monotonic()
    with pytest.raises(LearnerProcessError) as info:
        spawn_learners(_dies_body, 3, timeout_s=60, grace_s=20)
    elapsed = time.monotonic() - t0
    err = info.value
    assert "exited with code 1" in err.failures[2]
    for rank in (0, 1):  # the survivors raise instead of waiting for the dead peer
        msg = err.failures[rank]
        assert msg.startswith("PeerFailureError")
        assert f"Learner {rank} of 3" in msg and "'eta'" in msg
        assert "died or never joined" in msg and "resuming from the last checkpoint" in msg
    assert "rank 2" in str(err)
    # gloo sees the closed connection at once: far below the 30 s collective timeout
    assert elapsed < COMM_TIMEOUT_S, f"took {elapsed:.1f} s"


@pytest.mark.slow  # ~25 s of timeouts waited out
def test_the_last_barrier_can_wait_longer_than_an_exchange():
    """A learner late by more than the exchanges' timeout (its evaluation took longer):
    the plain barrier gives up, naming the failure; one given a longer bound waits,
    whichever rank is late (rank 0 coordinates gloo's monitored barrier: the others'
    wait for it is bounded by their group's timeout, not the barrier's)."""
    assert spawn_learners(_late_body, 2, args=(2.0, 4.0, 30.0), timeout_s=60) == [0, 1]
    assert spawn_learners(_late_body, 2, args=(2.0, 4.0, 30.0, 0), timeout_s=60) == [0, 1]
    with pytest.raises(LearnerProcessError) as info:
        spawn_learners(_late_body, 2, args=(2.0, 4.0, None), timeout_s=60, grace_s=10)
    assert info.value.failures[0].startswith("PeerFailureError")
    assert "barrier failed" in info.value.failures[0]


@pytest.mark.slow  # ~14 s; the dead learner above covers the common case
def test_a_silent_learner_times_out_and_is_terminated():
    timeout_s = 4.0
    t0 = time.monotonic()
    with pytest.raises(LearnerProcessError) as info:
        spawn_learners(_silent_body, 3, args=(timeout_s,), timeout_s=120, grace_s=2)
    elapsed = time.monotonic() - t0
    err = info.value
    for rank in (0, 1):
        assert err.failures[rank].startswith("PeerFailureError")
        assert "'tracker'" in err.failures[rank]
    assert "still running: terminated 2 s after rank" in err.failures[2]
    assert elapsed < 60, f"took {elapsed:.1f} s"


@pytest.mark.slow  # ~15 s of a timeout waited out; the dead learner above fails fast
def test_a_learner_that_never_joins_times_out_at_init():
    timeout_s = 6.0
    t0 = time.monotonic()
    # world size 3, but only ranks 0 and 1 are started
    out = spawn_learners(_never_joined_body, 2, args=(3, timeout_s), timeout_s=60)
    elapsed = time.monotonic() - t0
    for rank, (msg, seconds) in enumerate(out):
        assert msg is not None, f"rank {rank} formed a group without rank 2"
        assert f"Learner {rank}: could not form the group of 3 learners" in msg
        assert "died or never joined" in msg
        assert seconds < timeout_s + 5, f"rank {rank} gave up after {seconds:.1f} s"
    assert elapsed < timeout_s + 30


def test_spawn_reports_exceptions_and_terminates_the_rest():
    t0 = time.monotonic()
    with pytest.raises(LearnerProcessError, match="bad input on rank 0") as info:
        spawn_learners(_raise_or_sleep_body, 2, timeout_s=60, grace_s=1)
    assert time.monotonic() - t0 < 30
    err = info.value
    assert err.first_failed == 0 and "ValueError" in err.tracebacks[0]
    assert "still running" in err.failures[1]
    # a run where nothing fails is still bounded by timeout_s
    t0 = time.monotonic()
    with pytest.raises(LearnerProcessError, match="rank 0: still running: timed out after 3 s"):
        spawn_learners(_sleep_body, 1, timeout_s=3)
    assert time.monotonic() - t0 < 20


# ---------------------------------------------------------------------- in-process checks
@pytest.fixture
def single_group(monkeypatch):
    """A one-learner gloo group in the test process, formed from torchrun's environment
    variables (the default ``env://``), destroyed afterwards."""
    for key, value in {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(free_port()),
                       "RANK": "0", "WORLD_SIZE": "1"}.items():
        monkeypatch.setenv(key, value)
    comm = DistributedCommunicator(timeout_s=10, record=True)
    try:
        yield comm
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def test_single_learner_checks_and_group_reuse(single_group):
    comm = single_group
    assert comm.n_learners == 1 and comm.local_ids == [0]
    x = torch.randn(1, 4, dtype=torch.float64)
    assert torch.equal(comm.mix(x, torch.ones(1, 1), "eta"), x)
    with pytest.raises(ValueError, match="may not leave"):
        comm.all_gather(x, "cost_accrual")
    with pytest.raises(ValueError, match=r"Expected values \[1, \.\.\.\]"):
        comm.all_gather(torch.zeros(2, 4), "eta")
    with pytest.raises(ValueError, match="W must be"):
        comm.mix(x, torch.eye(2), "eta")
    assert [m.field for m in comm.messages] == ["eta"]
    comm.check_same_config("anything")
    # an existing group is reused and left open by the second communicator
    again = DistributedCommunicator()
    again.close()
    assert dist.is_initialized()
    with pytest.raises(ValueError, match="world_size=2"):
        DistributedCommunicator(world_size=2)
    comm.close()
    assert not dist.is_initialized()


def test_argument_checks(monkeypatch):
    for key in ("MASTER_ADDR", "MASTER_PORT", "RANK", "WORLD_SIZE"):
        monkeypatch.delenv(key, raising=False)
    with pytest.raises(ValueError, match="needs the environment variables"):
        DistributedCommunicator()
    with pytest.raises(ValueError, match="explicit rank and world_size"):
        DistributedCommunicator(init_method="tcp://127.0.0.1:1")
    with pytest.raises(ValueError, match="backend"):
        DistributedCommunicator(backend="mpi")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="needs CUDA"):
            DistributedCommunicator(backend="nccl")
    assert shard_for_rank(["a", "b", "c"], 1, world_size=3) == "b"
    with pytest.raises(ValueError, match="2 data shards for 3 learner processes"):
        shard_for_rank(["a", "b"], 0, world_size=3)
    with pytest.raises(ValueError, match="rank must lie"):
        shard_for_rank(["a", "b"], 2, world_size=2)
    with pytest.raises(ValueError, match="needs world_size"):
        shard_for_rank(["a"], 0)


def _object_body(rank, world_size, init_method):
    return MessageRecord(field="eta", shape=(3,), sender=rank)


def test_results_come_back_without_unpickling():
    """A learner's return value is read with torch.load(weights_only=True): an arbitrary
    object is refused with a clear message instead of being unpickled."""
    with pytest.raises(LearnerProcessError) as info:
        spawn_learners(_object_body, 1, timeout_s=60)
    assert "not plain data" in info.value.failures[0]
