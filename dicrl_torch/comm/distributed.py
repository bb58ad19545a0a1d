"""torch.distributed communicator: one process per learner (docs/design.md §5).

:class:`DistributedCommunicator` has the interface of
:class:`~dicrl_torch.comm.communicator.SimulatedCommunicator` and produces the same
numbers bit for bit: ``all_gather`` only copies float64 values, and ``mix`` applies the
shared :func:`~dicrl_torch.comm.communicator.fixed_order_mix` to the gathered values,
so a process performs exactly the floating-point operations that the simulated
backend performs for that learner's row.

Failure handling: the process group is created with a timeout, so a learner that
never joins makes ``init`` fail after ``timeout_s``, and a learner that dies makes the
next collective raise (gloo reports the closed connection at once, or times out after
``timeout_s``). Both surface as :class:`PeerFailureError`; nothing waits forever.
(With NCCL, collectives are asynchronous: NCCL's watchdog ends the process after the
timeout rather than raising.)

:func:`spawn_learners` starts ``N_L`` learner processes on localhost (tests and the
single-machine entry point); ``torchrun`` works too, through ``init_method="env://"``.
"""

from __future__ import annotations

import datetime
import hashlib
import multiprocessing.connection
import os
import socket
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from dicrl_torch.checks import InvalidSetting, setting_choice, setting_number
from dicrl_torch.comm.communicator import Communicator, check_control
from dicrl_torch.comm.compression import Compression

PATIENT_GROUP_S = 24 * 3600.0
"""The longest :meth:`DistributedCommunicator.barrier` can wait (its ``timeout_s``)."""

_FIX = ("A learner process died or never joined; check its log, then rerun, resuming "
        "from the last checkpoint.")


class PeerFailureError(RuntimeError):
    """A collective (or the rendezvous) failed because another learner is gone."""


class ConfigMismatchError(ValueError):
    """The learner processes were started with different configurations."""


class LearnerProcessError(RuntimeError):
    """One or more processes of :func:`spawn_learners` failed or timed out.

    Attributes:
        failures: ``rank -> "ExceptionType: message"`` (or why the process stopped).
        tracebacks: ``rank -> traceback text`` for ranks that raised.
        first_failed: the rank seen to fail first (usually the root cause), or None.
        results: ``rank -> return value`` of the ranks that did finish.
    """

    def __init__(self, failures: dict[int, str], tracebacks: dict[int, str],
                 first_failed: int | None, results: dict[int, Any] | None = None) -> None:
        self.failures, self.tracebacks, self.first_failed = failures, tracebacks, first_failed
        self.results = results or {}
        lines = [f"  rank {r}: {msg}" for r, msg in sorted(failures.items())]
        first = "" if first_failed is None else f" (rank {first_failed} failed first)"
        super().__init__(f"Learner process(es) {sorted(failures)} failed{first}:\n"
                         + "\n".join(lines))


class DistributedCommunicator(Communicator):
    """One learner per process over ``torch.distributed``: ``local_ids == [rank]``.

    Args:
        backend: "gloo" (CPU) or "nccl" (CUDA only; tensors are moved to this process's
            GPU for the collective and back).
        timeout_s: seconds before the rendezvous or a collective gives up on a peer.
        init_method: rendezvous URL; None means "env://" (``torchrun`` sets MASTER_ADDR,
            MASTER_PORT, RANK, WORLD_SIZE). "tcp://HOST:PORT" needs ``rank`` and
            ``world_size``.
        rank, world_size: this learner's id and ``N_L`` (default: from the environment).
        record: keep a :class:`~dicrl_torch.comm.communicator.MessageRecord` of every
            message this learner sends.
        compression, skip_redundant_rounds, diagnostics, link_failure, link_seed: see
            :class:`~dicrl_torch.comm.communicator.Communicator`.

    If the default process group already exists it is reused as it is (its backend and
    timeout apply) and left open by :meth:`close`. Every rank must call the collectives
    in the same order with the same shapes, as the trainer does.
    """

    @staticmethod
    def check_settings(**settings: Any) -> None:
        """Refuse the settings given (``backend``, ``timeout_s`` and
        :meth:`Communicator.check_settings`'s; others are ignored) as the constructor
        does: a config checks them before any process starts.

        Raises:
            InvalidSetting: naming the setting, what it must be and an example.
        """
        if "backend" in settings:
            backend = setting_choice("backend", settings["backend"], ("gloo", "nccl"),
                                     why="gloo: CPU; nccl: CUDA, one GPU per learner process")
            if backend == "nccl" and not torch.cuda.is_available():
                raise InvalidSetting("backend", backend, "'gloo' here ('nccl' needs CUDA, "
                                     "which this machine lacks)", "gloo")
        if "timeout_s" in settings:
            setting_number("timeout_s", settings["timeout_s"], low=0, low_open=True,
                           example=60, why="seconds a learner waits for the others")
        Communicator.check_settings(**settings)

    def __init__(self, *, backend: str = "gloo", timeout_s: float = 60.0,
                 init_method: str | None = None, rank: int | None = None,
                 world_size: int | None = None, record: bool = False,
                 compression: Compression | None = None, skip_redundant_rounds: bool = False,
                 diagnostics: bool = True, link_failure: float = 0.0,
                 link_seed: int = 0) -> None:
        if not dist.is_available():
            raise RuntimeError("torch.distributed is not available in this torch build; use "
                               "SimulatedCommunicator instead.")
        self.check_settings(backend=backend, timeout_s=timeout_s)
        self.timeout_s = float(timeout_s)
        self._owns_group = False
        if dist.is_initialized():
            backend = str(dist.get_backend())
        else:
            init_method = init_method or "env://"
            if init_method.startswith("tcp://") and (rank is None or world_size is None):
                raise ValueError(f"init_method={init_method!r} needs explicit rank and "
                                 f"world_size.")
            if init_method == "env://":
                needed = ["MASTER_ADDR", "MASTER_PORT"] + [
                    k for k, v in (("RANK", rank), ("WORLD_SIZE", world_size)) if v is None]
                missing = [k for k in needed if k not in os.environ]
                if missing:
                    raise ValueError(f"init_method='env://' needs the environment variables "
                                     f"{missing} (torchrun sets them); or pass init_method="
                                     f"'tcp://HOST:PORT' with rank and world_size.")
            if world_size is not None and world_size < 1:
                raise ValueError(f"world_size must be >= 1, got {world_size}.")
            if rank is not None and world_size is not None and not 0 <= rank < world_size:
                raise ValueError(f"rank must lie in [0, {world_size}), got {rank}.")
            try:
                dist.init_process_group(
                    backend, init_method=init_method,
                    rank=-1 if rank is None else rank,
                    world_size=-1 if world_size is None else world_size,
                    timeout=datetime.timedelta(seconds=self.timeout_s))
            except Exception as e:
                who = rank if rank is not None else os.environ.get("RANK", "?")
                size = world_size if world_size is not None else os.environ.get(
                    "WORLD_SIZE", "?")
                raise PeerFailureError(
                    f"Learner {who}: could not form the group of {size} learners at "
                    f"{init_method} within {self.timeout_s:g} s ({type(e).__name__}: "
                    f"{_first_line(e)}). {_FIX}") from e
            self._owns_group = True
        self.rank, self.n_learners = dist.get_rank(), dist.get_world_size()
        if rank is not None and rank != self.rank:
            raise ValueError(f"rank={rank} but the existing process group says {self.rank}.")
        if world_size is not None and world_size != self.n_learners:
            raise ValueError(f"world_size={world_size} but the existing process group has "
                             f"{self.n_learners} processes.")
        self.backend = backend
        self.device = torch.device("cpu")
        # gloo's monitored barrier waits for its ranks within the barrier's own bound on
        # rank 0 only: the others' send to rank 0 is bounded by their group's timeout. A
        # second group with a long one, formed now while every learner is here (forming
        # a group is itself a rendezvous), lets barrier() wait longer than an exchange.
        self._patient_group = (dist.new_group(backend="gloo", timeout=datetime.timedelta(
            seconds=PATIENT_GROUP_S)) if backend == "gloo" and self.n_learners > 1 else None)
        if backend == "nccl":
            # One GPU per learner process: torchrun's LOCAL_RANK, else round-robin.
            index = int(os.environ.get("LOCAL_RANK", self.rank % torch.cuda.device_count()))
            self.device = torch.device("cuda", index)
            torch.cuda.set_device(self.device)
        self._setup(record=record, compression=compression,
                    skip_redundant_rounds=skip_redundant_rounds, diagnostics=diagnostics,
                    link_failure=link_failure, link_seed=link_seed)

    @property
    def local_ids(self) -> list[int]:
        return [self.rank]

    # ------------------------------------------------------------------ collectives
    def _gather(self, payload: torch.Tensor, what: str) -> torch.Tensor:
        """all_gather a ``[1, ...]`` tensor -> ``[N_L, ...]`` on the payload's device."""
        send = payload.to(self.device).contiguous()
        out = [torch.empty_like(send) for _ in range(self.n_learners)]
        try:
            dist.all_gather(out, send)
        except Exception as e:
            raise PeerFailureError(
                f"Learner {self.rank} of {self.n_learners}: exchanging {what} failed "
                f"({type(e).__name__}: {_first_line(e)}). {_FIX}") from e
        return torch.cat(out).to(payload.device)

    def _exchange_dense(self, values: torch.Tensor, what: str) -> torch.Tensor:
        return self._gather(values, what)

    def _exchange_messages(self, messages: list[bytes], what: str) -> list[bytes]:
        """This learner's message to every other learner, and theirs to it: the 4-byte
        lengths by an all-gather (a collective, so a learner that died is noticed at
        once, as in every other exchange), then the bytes of each message not empty
        point to point; what crosses the backend is what
        :class:`~dicrl_torch.comm.traffic.Traffic` counts."""
        (mine,) = messages
        others = [r for r in range(self.n_learners) if r != self.rank]
        lengths = self._gather(torch.tensor([[len(mine)]], dtype=torch.int32), what)[:, 0]
        payloads = {r: torch.empty(int(lengths[r]), dtype=torch.uint8, device=self.device)
                    for r in others if int(lengths[r]) > 0}
        works = [dist.irecv(t, r) for r, t in payloads.items()]
        if mine:
            send = torch.frombuffer(bytearray(mine), dtype=torch.uint8).to(self.device)
            works += [dist.isend(send, r) for r in others]
        self._wait(works, what)
        return [mine if r == self.rank else
                bytes(payloads[r].cpu().numpy().tobytes()) if r in payloads else b""
                for r in range(self.n_learners)]

    def _wait(self, works: list, what: str) -> None:
        try:
            for work in works:
                work.wait(datetime.timedelta(seconds=self.timeout_s))
        except Exception as e:
            raise PeerFailureError(
                f"Learner {self.rank} of {self.n_learners}: exchanging {what} failed "
                f"({type(e).__name__}: {_first_line(e)}). {_FIX}") from e

    def gather_control(self, value, field: str) -> list:
        """Every learner's control ``value`` (JSON-able: the run directory, checkpointed
        iterations), in rank order. Sent as JSON bytes in a tensor, never pickled, and
        recorded in :attr:`messages` like the parameter vectors.

        Raises:
            ValueError: ``field`` is not a control field.
            PeerFailureError: another learner died or timed out.
        """
        import json

        data = check_control(field, value)
        size = self._gather(torch.tensor([[len(data)]], dtype=torch.int64), f"{field!r}")
        padded = torch.zeros(1, int(size.max()), dtype=torch.uint8)
        padded[0, :len(data)] = torch.frombuffer(bytearray(data), dtype=torch.uint8)
        rows = self._gather(padded, f"{field!r}")
        # what crossed: a length (int64) and the padded bytes, from and to every learner
        self._count(field, "control", (len(data),), [0] * self.n_learners,
                    [8 + padded.shape[1]] * self.n_learners, "json")
        return [json.loads(bytes(rows[r, :int(size[r, 0])].tolist()))
                for r in range(self.n_learners)]

    def barrier(self, timeout_s: float | None = None) -> None:
        """Wait for every learner (or raise :class:`PeerFailureError` after ``timeout_s``,
        default the communicator's; a longer one, up to :data:`PATIENT_GROUP_S`, needs the
        gloo backend, whose ``monitored_barrier`` takes its own bound)."""
        try:
            if self.backend == "nccl":
                dist.barrier(device_ids=[self.device.index])
            elif timeout_s is None or self._patient_group is None:
                dist.barrier()
            else:
                dist.monitored_barrier(group=self._patient_group,
                                       timeout=datetime.timedelta(seconds=float(timeout_s)))
        except Exception as e:
            raise PeerFailureError(f"Learner {self.rank} of {self.n_learners}: barrier failed "
                                   f"({type(e).__name__}: {_first_line(e)}). {_FIX}") from e

    def check_same_config(self, fingerprint: str) -> None:
        """Check that every learner was started with the same configuration.

        Exchanges only the sha256 digest of ``fingerprint`` (a control message, not
        learner data, hence not in :attr:`messages`); ``fingerprint`` must therefore
        describe the shared configuration, never a learner's demonstrations. Counted in
        the control traffic.

        Raises:
            ConfigMismatchError: on every rank, naming the ranks of each digest.
        """
        digest = hashlib.sha256(fingerprint.encode()).digest()
        mine = torch.tensor(list(digest), dtype=torch.int64).unsqueeze(0)  # [1, 32]
        gathered = self._gather(mine, "the configuration fingerprint")
        others, size = self.n_learners - 1, mine.numel() * 8
        for direction in ("sent", "received"):
            self.traffic.add(self.rank, direction, "control", messages=others, scalars=0,
                             nbytes=others * size)
        groups: dict[bytes, list[int]] = {}
        for r in range(self.n_learners):
            groups.setdefault(bytes(gathered[r].tolist()), []).append(r)
        if len(groups) > 1:
            majority = max(groups.values(), key=len)
            parts = "; ".join(f"ranks {ranks}: sha256 {key.hex()[:12]}"
                              for key, ranks in groups.items())
            differ = sorted(r for ranks in groups.values() if ranks is not majority
                            for r in ranks)
            raise ConfigMismatchError(
                f"Learner processes run different configurations ({parts}); ranks {differ} "
                f"differ from ranks {majority}. Start every learner with the same config "
                f"(only the rank and its data shard may differ).")

    def close(self) -> None:
        """Destroy the process group if this communicator created it (idempotent)."""
        if self._owns_group and dist.is_initialized():
            dist.destroy_process_group()
        self._owns_group = False

    def __enter__(self) -> DistributedCommunicator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def shard_for_rank(shards: Sequence, rank: int, *, world_size: int | None = None) -> Any:
    """The data shard of learner ``rank``: ``shards[rank]`` (learner id == rank).

    Args:
        shards: one shard per learner, in learner-id order.
        rank: this process's rank.
        world_size: ``N_L``; default: the initialised process group's size.
    """
    if world_size is None:
        if not (dist.is_available() and dist.is_initialized()):
            raise ValueError("shard_for_rank needs world_size when no process group is "
                             "initialised.")
        world_size = dist.get_world_size()
    if len(shards) != world_size:
        raise ValueError(f"{len(shards)} data shards for {world_size} learner processes; "
                         f"give exactly one shard per learner (shard i goes to rank i).")
    if not 0 <= rank < world_size:
        raise ValueError(f"rank must lie in [0, {world_size}), got {rank}.")
    return shards[rank]


# ---------------------------------------------------------------------- spawning
def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_learner(fn: Callable[..., Any], rank: int, world_size: int, init_method: str,
                 args: tuple, out_dir: str, num_threads: int | None) -> None:
    """Child process body: run ``fn`` and leave its outcome in ``out_dir/RANK.pt``.

    The outcome travels as a ``torch.save`` file that the parent reads with
    ``weights_only=True``: tensors, numbers, strings, None and lists, tuples and dicts of
    them. Nothing is unpickled, so ``fn`` must return plain data of that kind.
    """
    if num_threads is not None:
        torch.set_num_threads(num_threads)
    code = 0
    try:
        payload: tuple = ("ok", fn(rank, world_size, init_method, *args))
    except BaseException as e:  # report everything, including SystemExit
        payload, code = ("error", f"{type(e).__name__}: {e}", traceback.format_exc()), 1
    path = Path(out_dir) / f"{rank}.pt"
    # Write then rename, so the parent never reads a half-written file.
    tmp = path.with_suffix(".tmp")
    try:
        torch.save(payload, tmp)
    except Exception as e:
        torch.save(("error", f"return value could not be saved ({e})", ""), tmp)
        code = 1
    os.replace(tmp, path)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # skip interpreter teardown: no hang on a half-dead process group


def spawn_learners(fn: Callable[..., Any], n_learners: int, *, args: Sequence = (),
                   timeout_s: float = 120.0, port: int | None = None, grace_s: float = 10.0,
                   num_threads: int | None = 1) -> list[Any]:
    """Run ``fn(rank, world_size, init_method, *args)`` in ``n_learners`` processes and
    wait for them (:class:`LearnerProcesses`, whose arguments these are).

    Returns:
        Each rank's return value, in rank order.

    Raises:
        LearnerProcessError: a process raised, died, or outlived the timeout; the
            message names each failing rank with its exception text.
    """
    with LearnerProcesses(fn, n_learners, args=args, timeout_s=timeout_s, port=port,
                          grace_s=grace_s, num_threads=num_threads) as learners:
        return learners.wait()


class LearnerProcesses:
    """``n_learners`` processes running ``fn(rank, world_size, init_method, *args)``,
    started on entering the context; the starting process may work meanwhile
    (:meth:`failed` tells whether a learner has already failed) before it collects them
    with :meth:`wait`. Leaving the context terminates any still running.

    Processes use the "spawn" start method and rendezvous at ``tcp://127.0.0.1:PORT``.
    ``fn`` must be importable (module level) and return a picklable value.

    Args:
        fn: the learner's body; typically builds a :class:`DistributedCommunicator`
            with ``init_method=init_method, rank=rank, world_size=world_size``.
        n_learners: number of processes (the world size passed to ``fn``).
        args: extra picklable arguments for ``fn``.
        timeout_s: wall-clock bound for the whole run, from the start; then every
            process is killed.
        port: rendezvous port (default: a free one).
        grace_s: once a process has failed, how long the others may still run (to
            report their own errors) before they are terminated.
        num_threads: ``torch.set_num_threads`` in each child (None: leave torch's default).
    """

    def __init__(self, fn: Callable[..., Any], n_learners: int, *, args: Sequence = (),
                 timeout_s: float = 120.0, port: int | None = None, grace_s: float = 10.0,
                 num_threads: int | None = 1) -> None:
        if n_learners < 1:
            raise ValueError(f"n_learners must be >= 1, got {n_learners}.")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}.")
        self.fn, self.n_learners, self.args = fn, n_learners, tuple(args)
        self.timeout_s, self.port, self.grace_s = timeout_s, port, grace_s
        self.num_threads = num_threads
        self.procs: list = []

    def __enter__(self) -> LearnerProcesses:
        init_method = f"tcp://127.0.0.1:{self.port or free_port()}"
        ctx = mp.get_context("spawn")
        self._dir = tempfile.TemporaryDirectory(prefix="dicrl-learners-")
        self.procs = [ctx.Process(target=_run_learner, name=f"dicrl-learner-{r}",
                                  args=(self.fn, r, self.n_learners, init_method, self.args,
                                        self._dir.name, self.num_threads))
                      for r in range(self.n_learners)]
        try:
            for p in self.procs:
                p.start()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        self._start = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        try:
            _terminate(self.procs)
        finally:
            self._dir.cleanup()

    def failed(self) -> bool:
        """Whether a learner process has already exited with an error."""
        return any(p.exitcode not in (None, 0) for p in self.procs)

    def wait(self) -> list[Any]:
        """Wait for every process (bounded by ``timeout_s`` from the start, and by
        ``grace_s`` after a first failure), then collect them.

        Returns:
            Each rank's return value, in rank order.

        Raises:
            LearnerProcessError: a process raised, died, or outlived the timeout; the
                message names each failing rank with its exception text.
        """
        procs = self.procs
        stopped: dict[int, str] = {}
        failed_at: dict[int, float] = {}
        try:
            deadline = self._start + self.timeout_s
            while True:
                now = time.monotonic()
                for r, p in enumerate(procs):
                    if p.exitcode not in (None, 0) and r not in failed_at:
                        failed_at[r] = now
                alive = [p for p in procs if p.exitcode is None]
                if not alive:
                    break
                limit = deadline if not failed_at else min(
                    deadline, min(failed_at.values()) + self.grace_s)
                if now >= limit:
                    first = min(failed_at, key=failed_at.get) if failed_at else None
                    why = (f"timed out after {self.timeout_s:g} s" if now >= deadline else
                           f"terminated {self.grace_s:g} s after rank {first} failed")
                    for r, p in enumerate(procs):
                        if p.exitcode is None:
                            stopped[r] = f"still running: {why}"
                    break
                multiprocessing.connection.wait([p.sentinel for p in alive],
                                                timeout=min(limit - now, 1.0))
        finally:
            _terminate(procs)
        return _collect(procs, Path(self._dir.name), stopped, failed_at)


def _terminate(procs: list) -> None:
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        if p.pid is None:
            continue
        p.join(5.0)
        if p.is_alive():  # ignored SIGTERM
            p.kill()
            p.join(5.0)


def _collect(procs: list, out_dir: Path, stopped: dict[int, str],
             failed_at: dict[int, float]) -> list[Any]:
    results: dict[int, Any] = {}
    failures: dict[int, str] = {}
    tracebacks: dict[int, str] = {}
    for r, p in enumerate(procs):
        path = out_dir / f"{r}.pt"
        if r in stopped:
            failures[r] = stopped[r]
        elif not path.exists():
            failures[r] = (f"exited with code {p.exitcode} without returning a result "
                           f"(crashed or killed; see its output above)")
        else:
            try:
                payload = torch.load(path, weights_only=True)
            except Exception as e:  # an object that is not plain data: never unpickled
                failures[r] = (f"returned a value that is not plain data (tensors, numbers, "
                               f"strings, lists, tuples, dicts): {_first_line(e)}")
                continue
            if payload[0] == "ok":
                results[r] = payload[1]
                continue
            failures[r] = payload[1]
            tracebacks[r] = payload[2]
    if failures:
        first = min(failed_at, key=failed_at.get) if failed_at else None
        raise LearnerProcessError(failures, tracebacks, first, results)
    return [results[r] for r in range(len(procs))]


def _first_line(e: BaseException) -> str:
    """torch's distributed errors carry long C++ backtraces; keep the headline."""
    return str(e).strip().splitlines()[0] if str(e).strip() else repr(e)
