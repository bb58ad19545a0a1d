"""One run for every environment: build the trainers, train them with checkpoints and
exact resume, evaluate, run the baselines, and write ``results.json``, the table, the
figures and TensorBoard values (docs/design.md §2, §8).

An environment plugs in as a *task*, a subclass of :class:`~dicrl_torch.runs.task.Task`
(:class:`dicrl_torch.runs.grid.GridTask`, :class:`dicrl_torch.runs.continuous.SACTask`
and its games). The runner never reads a config: the entry point (``experiments/train.py``)
builds the task, the :class:`RunSettings`, the :class:`TrainerSpec` and the
communicators, and calls :func:`run_all_in_one` (every learner in this process) or, one
process per learner, :func:`run_learner` in each and :func:`finish` in the main one.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dicrl_torch.algos.callbacks import InnerScalars
from dicrl_torch.algos.dicrl import DICRL, StepSizes, check_trainer_options
from dicrl_torch.algos.greedy import ResumeMismatchError
from dicrl_torch.checks import setting_bool, setting_int
from dicrl_torch.figures import save_png
from dicrl_torch.io import write_json
from dicrl_torch.runs.callbacks import CheckpointEvery, OuterMetrics, RunOf, TensorBoardValues
from dicrl_torch.runs.checkpoints import Checkpoints, progress_of
from dicrl_torch.runs.results import (
    OBSTACLE_COLUMNS,
    REGION_COLUMNS,
    print_table,
    print_timings,
    results_record,
)
from dicrl_torch.runs.signals import Interrupted, StopOnSignal, stoppable
from dicrl_torch.runs.task import Rollouts, Task

FINAL_WAIT_S = 6 * 3600.0
"""Seconds a learner process waits, after writing its row, for the slowest learner's."""


@dataclass
class RunSettings:
    """How a run trains, evaluates and stores (everything but the task and trainers).

    Attributes:
        experiment: its name (``results.json``'s ``experiment``).
        config: the resolved config as plain dicts, stored in ``results.json``.
        training_config: what a checkpoint must match to resume
            (:func:`dicrl_torch.runs.checkpoints.training_config`).
        outer_iterations, eval_every, checkpoint_every: outer iterations to train, between
            CR/CVR rollouts of the curves, between checkpoints.
        resume: continue from the run directory's checkpoints.
        run_d_icrl, run_c_icrl: which bi-level methods to train.

    Raises:
        InvalidSetting: a setting out of range, naming it (checked on construction).
    """

    experiment: str
    config: dict
    training_config: dict
    outer_iterations: int
    eval_every: int = 5
    checkpoint_every: int = 1
    resume: bool = False
    run_d_icrl: bool = True
    run_c_icrl: bool = True

    def __post_init__(self) -> None:
        self.outer_iterations = setting_int("outer_iterations", self.outer_iterations,
                                            example=20)
        self.eval_every = setting_int(
            "eval_every", self.eval_every, example=5,
            why="outer iterations between the CR/CVR evaluations of the curves")
        self.checkpoint_every = setting_int("checkpoint_every", self.checkpoint_every,
                                            example=1, why="outer iterations between "
                                                           "checkpoints")
        self.resume = setting_bool("resume", self.resume)
        self.run_d_icrl = setting_bool("run_d_icrl", self.run_d_icrl)
        self.run_c_icrl = setting_bool("run_c_icrl", self.run_c_icrl)


@dataclass
class TrainerSpec:
    """The D-ICRL trainer's settings for any number of learners.

    Attributes:
        schedules: ``n_learners -> (inner W(k), outer W̄(n))`` mixing schedules.
        steps: step sizes of the distributed run.
        inner_step: the constant step of ``inner_method="gradient_tracking"``.
        n_shards: the number of learners of the distributed run (``len(split)``).
        options: the other :class:`~dicrl_torch.algos.dicrl.DICRL` keyword arguments.

    Raises:
        InvalidSetting: an option out of range, naming it (checked on construction, as
            the trainer would: :func:`~dicrl_torch.algos.dicrl.check_trainer_options`).
    """

    schedules: Callable[[int], tuple[Any, Any]]
    steps: StepSizes
    inner_step: float
    n_shards: int
    options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_trainer_options(inner_step=self.inner_step, **self.options)

    def kwargs(self, n_learners: int) -> dict[str, Any]:
        """Keyword arguments of a trainer of ``n_learners`` learners (C-ICRL: 1).

        Consensus averages the learners' steps α m^[v] ∇G^[v] into α (m / N_L) ∇G; one
        learner with all m trajectories takes the same step on G with α / N_L.
        """
        scale = n_learners / self.n_shards
        inner, outer = self.schedules(n_learners)
        return dict(inner_schedule=inner, outer_schedule=outer,
                    steps=dataclasses.replace(self.steps,
                                              alpha_bar=self.steps.alpha_bar * scale),
                    inner_step=self.inner_step * scale, **self.options)


def make_trainer(task: Task, spec: TrainerSpec, shards: Sequence, communicator,
                 trajectory_counts: Sequence[int], stream: int,
                 progress: bool = True) -> DICRL:
    """The trainer of the learners ``communicator.local_ids`` (holding ``shards``), starting
    from the task's :meth:`~dicrl_torch.runs.task.Task.initial_weights` where it fixes them.

    Raises:
        ValueError: the trainer spec's options give other initial weights than the task.
    """
    kwargs = spec.kwargs(communicator.n_learners)
    for key, value in task.initial_weights().items():
        if key in spec.options and float(spec.options[key]) != value:
            raise ValueError(
                f"The task starts from {key}={value} (its warm-up trained there) but the "
                f"trainer spec's options say {key}={spec.options[key]}; give it once, to "
                f"the task (drop it from TrainerSpec.options).")
        kwargs[key] = value
    return DICRL(learner_model=task.learner_model(communicator.local_ids, shards, stream),
                 shards=list(shards), trajectory_counts=list(trajectory_counts),
                 communicator=communicator, progress=progress, **kwargs)


def file_stem(name: str) -> str:
    """A method's name as a file or TensorBoard run name: ``M(C)E-greedy`` -> ``MCE-greedy``."""
    return re.sub(r"[^\w.-]", "", name)


def run_name(method: str, learner: int) -> str:
    """A method's TensorBoard run: ``learner<v>`` for D-ICRL, ``c_icrl``, ``me_greedy``..."""
    if method == "D-ICRL":
        return f"learner{learner}"
    return file_stem(method).lower().replace("-", "_")


def log_row(task: Task, logger, run: str, label: str, row: dict, rollouts: Rollouts,
            step: int, png: Path) -> None:
    """A table row's constraint map, drawn with the rollouts the row was measured on
    (PNG and TensorBoard; none where the task draws none), and its final ``eval/``
    values."""
    img = task.constraint_map(label, row, rollouts)
    if img is not None:
        logger.image(run, "eval/constraint_map", img, step)
        save_png(png, img)
    for key in ("CR", "CVR", "SR", *REGION_COLUMNS, *OBSTACLE_COLUMNS):
        value = row.get("CR_mean" if key == "CR" else key)
        if value is not None:
            logger.scalar(run, f"eval/{key}", value, step)
    for tag, value, at in task.row_scalars(row):
        logger.scalar(run, tag, value, at)


# ---------------------------------------------------------------------- one method
def train_method(name: str, trainer: DICRL, *, task: Task, settings: RunSettings,
                 ckpt: Checkpoints, logger, run_of: RunOf, log_network: bool,
                 stop: StopOnSignal | None = None) -> None:
    """Train to ``settings.outer_iterations`` with metrics in the history, TensorBoard
    values and checkpoints (the trainer continues from its loaded state).

    Raises:
        Interrupted: ``stop`` caught a signal; the last outer iteration is checkpointed.
    """
    values = TensorBoardValues(logger, run_of, log_network)
    values.replay(trainer)
    callbacks = [InnerScalars(logger, run_of),
                 OuterMetrics(task, settings.eval_every, settings.outer_iterations),
                 values, CheckpointEvery(ckpt, name, settings.checkpoint_every, stop)]
    with stoppable(stop):
        trainer.train(settings.outer_iterations, callbacks=callbacks)
    ckpt.save(name, trainer)


def evaluate_method(name: str, trainer: DICRL, *, task: Task, settings: RunSettings,
                    ckpt: Checkpoints, logger, run_of: RunOf, out: Path,
                    progress: bool = True) -> list[dict]:
    """Rows, constraint maps and final TensorBoard values of the trainer's local learners.

    The rows are checkpointed; a resumed run takes them from there instead of evaluating
    again (for the grid: pruning, minutes per learner at 3 experts). The checkpoint keeps
    no rollouts: such a row's map is drawn without them.
    """
    evaluation, n = task.evaluation_settings(), trainer.state.outer_iteration
    saved = ckpt.evaluated_rows(name, n, evaluation)
    if saved is not None:
        print(f"{name}: rows evaluated after outer iteration {n} taken from {ckpt.path}")
    task.before_evaluation(trainer)
    rows = []
    step = settings.outer_iterations
    for i, v in enumerate(trainer.local):
        label = f"{name} learner {v + 1}"
        if saved is None:
            t0 = time.perf_counter()
            row, rollouts = task.evaluate_learner(trainer, i, progress)
            print(f"evaluated {label} in {time.perf_counter() - t0:.0f} s", flush=True)
        else:
            row, rollouts = saved[i], ()
        log_row(task, logger, run_of(v), label, row, rollouts, step,
                out / f"constraints_{file_stem(name)}_{v + 1}.png")
        rows.append(row)
    if saved is None:
        ckpt.save_rows(name, n, evaluation, rows)
    return rows


# ---------------------------------------------------------------------- baselines
def run_greedy(name: str, greedy, ckpt: Checkpoints, stop: StopOnSignal | None):
    """One greedy baseline, checkpointed (as ``name``) after every candidate it evaluates
    and continued from its saved progress on resume (a greedy that is not ``resumable``
    is run again from the start).

    Raises:
        Interrupted: ``stop`` caught a signal; the last evaluated candidate is saved.
    """
    saved = ckpt.states(name)
    record = saved[0]["greedy"] if saved else None
    if record is not None and not greedy.resumable:
        # Its model (e.g. SAC's warm-started policy) is not in the checkpoint, only the
        # constraints it added; seeded, it repeats the same steps from the start.
        print(f"{name}: its progress in {ckpt.path} cannot be continued (its model is more "
              f"than the constraint set); running it again from the start", flush=True)
        record = None

    def save(record: dict) -> None:
        ckpt.save_state(name, {"greedy": record,
                               "outer_iteration": record["evaluated"] + record["finished"]})
        if stop is not None and stop.signum is not None:
            stop.training = False
            raise Interrupted(stop.signum, f"{name} saved {progress_of(ckpt.saved[name])}")

    try:
        with stoppable(stop):  # a first signal lets the current candidate finish
            return greedy.run(resume_from=record, on_step=save)
    except ResumeMismatchError as e:
        raise ResumeMismatchError(f"{e} (The progress is {name} in {ckpt.path}; resume with "
                                  f"the interrupted run's baselines.epsilon and "
                                  f"baselines.max_constraints.)") from e


def run_baselines(task: Task, trained_rows: dict[str, dict], *, logger, out: Path,
                  ckpt: Checkpoints, stop: StopOnSignal | None = None
                  ) -> tuple[dict, dict, dict]:
    """The task's greedy baselines: their table rows, per-step histories and seconds
    (every resumed segment counted).

    Every greedy step (a constraint added) logs ``eval/FPR``, ``eval/FNR`` and
    ``greedy/log_likelihood`` at step ``k`` = constraints added so far, under the run
    named after the baseline (``me_greedy``); the final policy is evaluated as the
    other rows, by the task given the greedy itself (:meth:`Task.baseline_row`).
    """
    methods, histories, seconds = {}, {}, {}
    for name, greedy in task.make_baselines(trained_rows).items():
        res = run_greedy(name, greedy, ckpt, stop)
        run = run_name(name, 0)
        row, history, rollouts = task.baseline_row(name, greedy, res)
        for h in history:
            for key, tag in (("FPR", "eval/FPR"), ("FNR", "eval/FNR"),
                             ("log_likelihood", "greedy/log_likelihood")):
                if h.get(key) is not None:
                    logger.scalar(run, tag, h[key], h["step"])
        log_row(task, logger, run, name, row, rollouts, len(res.added),
                out / f"constraints_{file_stem(name)}.png")
        methods[name] = {"D": "×", "NATR": "×", "learners": [row]}
        histories[name] = history
        seconds[name] = res.seconds
    return methods, histories, seconds


# ---------------------------------------------------------------------- the run's end
def run_c_icrl(task: Task, spec: TrainerSpec, *, settings: RunSettings, out: Path, logger,
               ckpt: Checkpoints, communicator, stop: StopOnSignal | None = None) -> dict:
    """C-ICRL on the pooled demonstrations, trained (checkpointed as ``C-ICRL``,
    continued from there on resume) and evaluated: its ``learners`` rows and
    ``history``."""
    pooled = task.demos  # every learner's trajectories, in learner order
    c = make_trainer(task, spec, [pooled], communicator, [sum(task.split)], stream=1)
    if states := ckpt.states("C-ICRL"):
        c.load_state_dict(states[0])
    c_icrl = lambda v: "c_icrl"  # noqa: E731
    train_method("C-ICRL", c, task=task, settings=settings, ckpt=ckpt, logger=logger,
                 run_of=c_icrl, log_network=False, stop=stop)
    rows = evaluate_method("C-ICRL", c, task=task, settings=settings, ckpt=ckpt,
                           logger=logger, run_of=c_icrl, out=out)
    return {"learners": rows, "history": c.history}


def finish(task: Task, settings: RunSettings, spec: TrainerSpec, *, out: Path,
           d_icrl: dict | None, logger, ckpt: Checkpoints, t_start: float, c_icrl_comm,
           stop: StopOnSignal | None = None, c_icrl: dict | None = None) -> dict:
    """C-ICRL, the baselines and the reference rows (in this process), then
    ``results.json``, the table and the figures.

    Args:
        d_icrl: the D-ICRL ``learners`` rows, ``history`` and final ``disagreement``;
            None when it was not trained.
        c_icrl: C-ICRL's :func:`run_c_icrl`, when it ran beside the learner processes;
            None: run it here.

    Returns:
        ``results.json``'s record.
    """
    task.bind_run_dir(out, settings.training_config)
    methods: dict = {}
    histories: dict = {}
    if d_icrl is not None:
        methods["D-ICRL"] = {"D": "✓" if len(task.split) > 1 else "×", "NATR": "✓",
                             "learners": d_icrl["learners"]}
        histories["D-ICRL"] = d_icrl["history"]
    if settings.run_c_icrl:
        if c_icrl is None:
            c_icrl = run_c_icrl(task, spec, settings=settings, out=out, logger=logger,
                                ckpt=ckpt, communicator=c_icrl_comm, stop=stop)
        methods["C-ICRL"] = {"D": "×", "NATR": "✓", "learners": c_icrl["learners"]}
        histories["C-ICRL"] = c_icrl["history"]
    baseline_rows, baseline_histories, baseline_seconds = run_baselines(
        task, dict(methods), logger=logger, out=out, ckpt=ckpt, stop=stop)
    methods.update(baseline_rows)  # before the experts: the paper's row order
    histories.update(baseline_histories)
    identifiability = task.annotate(methods)
    for name, row in task.reference_rows().items():
        methods[name] = {"learners": [row]}
    results = results_record(
        experiment=settings.experiment, config=settings.config, t_start=t_start,
        methods=methods, disagreement=None if d_icrl is None else d_icrl["disagreement"],
        histories=histories, baseline_seconds=baseline_seconds)
    if identifiability is not None:  # its time beside the other timings, not in the record
        results["identifiability_s"] = identifiability.pop("seconds")
    results["identifiability"] = identifiability
    for name, m in methods.items():  # the rows' final values the evaluation did not log
        for v, row in enumerate(m["learners"]):
            if row.get("FNR_required") is not None:
                logger.scalar(run_name(name, v), "eval/FNR_required", row["FNR_required"],
                              settings.outer_iterations)
    write_json(out / "results.json", results)
    # After results.json: a figure that fails to draw loses no result.
    images = task.figures(methods=methods, histories=results["history"],
                          experiment=settings.experiment, eval_every=settings.eval_every)
    d_history = results["history"].get("D-ICRL") or []
    if d_history and all(h.get("bytes_sent") is not None for h in d_history):
        from dicrl_torch.figures import metrics_against_bytes

        images["traffic"] = metrics_against_bytes(
            {"D-ICRL": d_history},
            title=f"{settings.experiment}: each learner's metrics against the bytes it sent")
    paths = []
    for tag, img in images.items():
        paths.append(save_png(out / f"{tag}.png", img))
        logger.image("figures", tag, img, settings.outer_iterations)
    logger.close()
    print()
    print_table(methods, (*task.columns, "KB_sent"))
    if identifiability is not None:
        i = identifiability
        print(f"true constraints: {i['n_demonstrated']} demonstrated, {i['n_required']} "
              f"required, {i['n_undetermined']} undetermined by the demonstrations "
              f"(undetermined: {', '.join(i['undetermined']) or 'none'})")
    print_timings(results, resumed=settings.resume)
    print(f"results, TensorBoard runs (tb/) and figures in {out.resolve()}")
    print("figures:\n" + "\n".join(f"  {path.resolve()}" for path in paths))
    return results


def run_all_in_one(task: Task, settings: RunSettings, spec: TrainerSpec, *, out: Path,
                   t_start: float, communicator: Callable[[int], Any], logger) -> dict:
    """Every learner in this process (``comm=simulated``): D-ICRL, then :func:`finish`.

    A first SIGINT/SIGTERM finishes the current outer iteration (or greedy candidate),
    checkpoints it and raises :class:`Interrupted`; a second one stops at once.

    Args:
        communicator: ``n_learners -> communicator`` (D-ICRL's and C-ICRL's).
    """
    with StopOnSignal() as stop:
        # The checkpoint is read (and checked against the config) before any computation.
        ckpt = Checkpoints(out / "checkpoint.pt", settings.resume,
                           config=settings.training_config)
        task.bind_run_dir(out, settings.training_config)
        task.announce(out)
        d_icrl = None
        if settings.run_d_icrl:
            trainer = make_trainer(task, spec, task.shards, communicator(len(task.split)),
                                   task.split, stream=0)
            if states := ckpt.states("D-ICRL"):
                trainer.load_state_dict(states[0])
            run_of = lambda v: f"learner{v}"  # noqa: E731
            train_method("D-ICRL", trainer, task=task, settings=settings, ckpt=ckpt,
                         logger=logger, run_of=run_of, log_network=True, stop=stop)
            gap = final_disagreement(trainer)  # of the trained ω_c: pruning below is local
            rows = with_traffic(trainer, evaluate_method(
                "D-ICRL", trainer, task=task, settings=settings, ckpt=ckpt, logger=logger,
                run_of=run_of, out=out))
            d_icrl = {"learners": rows, "history": trainer.history, "disagreement": gap}
        return finish(task, settings, spec, out=out, d_icrl=d_icrl, logger=logger, ckpt=ckpt,
                      t_start=t_start, c_icrl_comm=communicator(1), stop=stop)


def final_disagreement(trainer: DICRL) -> float | None:
    """The trained ω_c's consensus distance (a diagnostic round), None when the
    communicator's diagnostics are off."""
    return trainer.disagreement() if getattr(trainer.comm, "diagnostics", True) else None


TRAFFIC_KEYS = ("traffic", "KB_sent")


def with_traffic(trainer: DICRL, rows: list[dict]) -> list[dict]:
    """``rows`` of the local learners with what each sent and received (``traffic``, by
    phase) and ``KB_sent``, the algorithm's kilobytes sent (the table's column)."""
    for v, row in zip(trainer.local, rows, strict=True):
        row["traffic"] = trainer.comm.traffic.report(v)
        row["KB_sent"] = row["traffic"]["algorithm_bytes_sent"] / 1000
    return rows


# ---------------------------------------------------------------------- one process per learner
def resume_learner(comm, ckpt: Checkpoints, trainer: DICRL) -> None:
    """Load the newest checkpointed outer iteration that every learner has.

    A learner that dies between the last exchange of an outer iteration and its
    checkpoint is one save behind the others; they then use their previous save. Which
    iterations each learner holds is exchanged through the communicator (audited).
    """
    have = {int(sd["outer_iteration"]): sd for sd in ckpt.states("D-ICRL")}
    every = comm.gather_control(sorted(have), "checkpointed_iterations")
    start = min(max(h, default=0) for h in every)
    if start == 0:
        if any(every) and comm.rank == 0:
            print(f"learners {[r for r, h in enumerate(every) if not h]} have no checkpoint; "
                  f"every learner starts from scratch")
        return
    lacking = [r for r, h in enumerate(every) if start not in h]
    if lacking:
        raise ValueError(
            f"The learners' checkpoints share no outer iteration (saved: "
            f"{dict(enumerate(every))}); learners {lacking} have none at {start}. Delete "
            f"checkpoint_rank*.pt in the run directory to start over.")
    trainer.load_state_dict(have[start])
    if comm.rank == 0:
        print(f"D-ICRL learners continue after outer iteration {start}")


def agree_on_run_dir(comm, out: Path) -> tuple[Path, str]:
    """Rank 0's run directory and a run id. Hydra names the default directory after the
    second it started in, which can differ between the processes torchrun starts; the
    others' (still empty) directories are removed."""
    root, run_id = comm.gather_control([str(out.resolve()), uuid.uuid4().hex],
                                       "run_directory")[0]
    root = Path(root)
    if root != out.resolve():
        if out.is_dir() and {q.name for q in out.iterdir()} <= {".hydra", "train.log"}:
            shutil.rmtree(out, ignore_errors=True)
        root.mkdir(parents=True, exist_ok=True)
    return root, run_id


def run_learner(comm, task: Task, settings: RunSettings, spec: TrainerSpec, *, out: Path,
                run_id: str, logger, sharing: int | None = None) -> None:
    """Learner ``comm.rank``: train on its own shard, evaluate its row, write it to
    ``learner_rows/rank<r>.json`` and wait for the others.

    Args:
        sharing: how many processes share the task's once-per-run work
            (:meth:`Task.bind_run_dir`): the learners (default), one more when C-ICRL
            trains beside them (as the last).
    """
    rank = comm.rank
    task.bind_run_dir(out, settings.training_config, process=rank,
                      processes=comm.n_learners if sharing is None else sharing)
    shard = task.shards[rank]
    if shard is None:
        raise ValueError(f"Learner {rank} holds no demonstrations in this process.")
    trainer = make_trainer(task, spec, [shard], comm, task.split, stream=0,
                           progress=rank == 0)
    ckpt = Checkpoints(out / f"checkpoint_rank{rank}.pt", settings.resume, keep_previous=True,
                       crash_tags=(f"D-ICRL@rank{rank}",), config=settings.training_config)
    resume_learner(comm, ckpt, trainer)
    run_of = lambda v: f"learner{v}"  # noqa: E731
    train_method("D-ICRL", trainer, task=task, settings=settings, ckpt=ckpt, logger=logger,
                 run_of=run_of, log_network=rank == 0)
    gap = final_disagreement(trainer)  # of the trained ω_c, as in the simulated run
    rows = with_traffic(trainer, evaluate_method(
        "D-ICRL", trainer, task=task, settings=settings, ckpt=ckpt, logger=logger,
        run_of=run_of, out=out, progress=rank == 0))
    logger.close()
    write_json(out / "learner_rows" / f"rank{rank}.json", {
        "run_id": run_id, "rank": rank, "world_size": comm.n_learners, "row": rows[0],
        "history": trainer.history, "disagreement": gap})
    # The learners' evaluations can differ by minutes (100 planned drone episodes each),
    # far beyond the exchanges' timeout; a learner that dies meanwhile is noticed by the
    # spawning process (or torchrun), which stops the others.
    comm.barrier(timeout_s=FINAL_WAIT_S)


def merge_learner_rows(out: Path, n_learners: int, run_id: str) -> dict:
    """The D-ICRL rows, history and disagreement of :func:`run_learner`'s files."""
    parts = []
    for r in range(n_learners):
        path = out / "learner_rows" / f"rank{r}.json"
        part = json.loads(path.read_text()) if path.exists() else None
        if part is None or part["run_id"] != run_id:
            why = "is missing" if part is None else "is from another run"
            raise FileNotFoundError(
                f"{path} {why}. Every learner writes its row into the run directory: "
                f"give all processes the same one (multi-node runs: hydra.run.dir on a "
                f"shared file system).")
        parts.append(part)
    # One history entry per outer iteration; per-learner lists are concatenated in rank
    # order (learner id == rank), the rest (iteration, inner processes) is global.
    history = [{k: [x for part in parts for x in part["history"][j][k]]
                if isinstance(v, list) else v for k, v in entry.items()}
               for j, entry in enumerate(parts[0]["history"])]
    return {"learners": [part["row"] for part in parts], "history": history,
            "disagreement": parts[0]["disagreement"]}
