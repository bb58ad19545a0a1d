"""Pieces every experiment entry point shares: building configured objects, atomic
result files, the logger and the results table (DESIGN §8)."""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import OmegaConf


def build(cfg, **objects):
    """Instantiate ``cfg`` with built objects as keyword arguments."""
    return instantiate(cfg, _partial_=True)(**objects)


@dataclasses.dataclass
class GridParts:
    """The grid world's pieces as every grid entry point builds them from the config."""

    layout: Any
    model: Any
    solver: Any
    reward_basis: Any
    cost_basis: Any
    true_reward_weights: Any  # [N * l_r] ω_rE in the reward basis' layout

    def true_reward_table(self):
        """``[N, S1]`` each expert's true reward in each cell (the reward is a state's)."""
        return self.reward_basis().weighted(self.true_reward_weights).local[:, :, 0]


def build_grid(cfg) -> GridParts:
    """Layout, the learner's model, the solver and both feature bases from ``cfg``."""
    layout = instantiate(cfg.env.layout)
    model = build(cfg.env.model, layout=layout)
    reward_basis = build(cfg.features.reward, model=model)
    return GridParts(
        layout=layout, model=model, solver=build(cfg.solver, model=model),
        reward_basis=reward_basis, cost_basis=build(cfg.features.cost, model=model),
        true_reward_weights=reward_basis.true_weights(tuple(cfg.env.true_reward_weights)))


def atomic_write(path: Path, write: Callable[[Path], Any]) -> None:
    """``write(tmp)`` then rename ``tmp`` to ``path``: readers see the old file or the new
    one, never half of one. An exception (or an interrupting signal) removes ``tmp``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        write(tmp)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def trainer_settings(cfg, n_learners: int) -> dict[str, Any]:
    """The :class:`~dicrl_torch.algos.dicrl.DICRL` keyword arguments read from ``cfg.algo``
    and ``cfg.graph``, for a run of ``n_learners`` learners (C-ICRL: 1) whatever the
    environment; the caller adds the learner model, shards and communicator."""
    a = cfg.algo
    graph = {k: build(cfg.graph[k], n_learners=n_learners) for k in ("inner", "outer")}
    # Consensus averages the learners' steps α m^[v] ∇G^[v] into α (m / N_L) ∇G; one
    # learner with all m trajectories takes the same step on G with α / N_L.
    steps = instantiate(a.steps)
    scale = n_learners / len(cfg.split)
    steps = dataclasses.replace(steps, alpha_bar=steps.alpha_bar * scale)
    return dict(inner_schedule=graph["inner"], outer_schedule=graph["outer"], steps=steps,
                inner_steps=a.inner_steps, lsca_curvature=a.lsca_curvature,
                prune_accrued=a.prune_accrued, init_cost_weights=a.init_cost_weights,
                init_reward_weights=a.init_reward_weights, init_multiplier=a.init_multiplier,
                inner_method=a.inner_method, inner_step=a.inner_step * scale)


def write_json(path: Path, obj) -> None:
    text = json.dumps(obj, indent=1)  # before opening anything: a failure writes nothing
    atomic_write(path, lambda tmp: tmp.write_text(text))


def results_record(cfg, *, t_start: float, methods: dict, disagreement: float | None,
                   histories: dict[str, list[dict]],
                   baseline_seconds: dict[str, float] | None = None) -> dict:
    """``results.json`` (DESIGN §8) of a finished run.

    Two entries are timings, the only ones in which two runs of the same seed differ:
    ``wall_s``, this process's time since ``t_start``, and ``training_s``, each trained
    method's outer iterations summed over every process that ran them, and each greedy
    baseline's ``baseline_seconds`` (its candidates' solves, also summed over resumes).
    A run resumed across sessions thus still reports what its training took (its
    ``wall_s`` counts only the last segment). For the same reason the history's
    per-iteration ``seconds`` are left out.
    """
    training_s = {k: sum(h["seconds"] for h in hist) for k, hist in histories.items()
                  if hist and all(h.get("seconds") is not None for h in hist)}
    return {
        "experiment": cfg.name, "wall_s": time.perf_counter() - t_start,
        "training_s": {**training_s, **(baseline_seconds or {})},
        "methods": {k: {"learners": v["learners"]} for k, v in methods.items()},
        "consensus_max_pairwise_cost_distance": disagreement,
        "history": {k: [{**h, "seconds": None} for h in hist] for k, hist in histories.items()},
        "config": OmegaConf.to_container(cfg, resolve=True),
    }


def print_timings(results: dict, resumed: bool) -> None:
    """The run's wall time and final consensus; for a ``resumed`` run also the training
    time of its methods, counting the segments before the resume."""
    gap = results["consensus_max_pairwise_cost_distance"]
    print(f"\nwall time {results['wall_s']:.0f} s"
          + ("" if gap is None else f"; consensus max ‖ω_c − ω_c'‖ = {gap:.1e}"))
    if resumed and results["training_s"]:
        print("training, every segment of the resumed run counted: "
              + ", ".join(f"{k} {s:.0f} s" for k, s in results["training_s"].items()))


def make_logger(cfg, out: Path):
    return instantiate(cfg.logger, **({"root": out / "tb"} if "TensorBoard" in
                                      cfg.logger._target_ else {}))


def log_disagreement(logger, trainer, n: int) -> None:
    """The network run's ``consensus/`` distances after outer iteration ``n``: of ω_c
    and of η̄. Gathers from every learner, so every learner process must call it;
    ``logger`` None: take part without logging (the processes that do not own
    ``network``)."""
    gaps = {tag: trainer.disagreement(field)
            for tag, field in (("consensus/max_pairwise_cost_distance", "cost_weights"),
                               ("consensus/max_pairwise_eta_distance", "eta"))}
    if logger is not None:
        for tag, gap in gaps.items():
            logger.scalar("network", tag, gap, n)


# The paper's Table 1 (grid world) and Table 2 (drones) metric columns.
TABLE1_COLUMNS = ("CR", "FPR", "FNR", "CVR", "RFD")
TABLE2_COLUMNS = ("FPR", "FNR", "CVR", "SR")
_FORMATS = {"FPR": (7, ".2f"), "FNR": (7, ".2f"), "CVR": (8, ".3f"), "RFD": (8, ".3f"),
            "SR": (7, ".2f")}


def print_table(methods: dict, columns: Sequence[str] = TABLE1_COLUMNS) -> None:
    """Print ``methods`` (``{name: {"D", "NATR", "learners": [row, ...]}}``) in the paper's
    layout: one line per learner, a metric that does not apply as N/A."""
    fmt = lambda x, f: "N/A" if x is None else format(x, f)  # noqa: E731
    head = f"{'':26s}{'D':>3s}{'NATR':>6s}"
    for c in columns:
        head += f"{'CR':>20s}" if c == "CR" else f"{c:>{_FORMATS[c][0]}s}"
    print(head)
    for name, m in methods.items():
        for j, r in enumerate(m["learners"]):
            label = f"{name} {j + 1}" if len(m["learners"]) > 1 else name
            line = f"{label:26s}{m.get('D', 'N/A'):>3s}{m.get('NATR', 'N/A'):>6s}"
            for c in columns:
                if c == "CR":
                    line += (f"{r['CR_mean']:11.2f} ± {r['CR_std']:6.2f}"
                             if r.get("CR_mean") is not None else f"{'N/A':>20s}")
                else:
                    width, f = _FORMATS[c]
                    line += f"{fmt(r.get(c), f):>{width}s}"
            print(line)
