"""``results.json`` and the printed table of a finished run (docs/design.md §8)."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any


def results_record(*, experiment: str, config: Mapping[str, Any], t_start: float,
                   methods: dict, disagreement: float | None,
                   histories: dict[str, list[dict]],
                   baseline_seconds: dict[str, float] | None = None) -> dict:
    """``results.json`` of a finished run.

    Two entries are timings, the only ones in which two runs of the same seed differ:
    ``wall_s``, this process's time since ``t_start``, and ``training_s``, each trained
    method's outer iterations summed over every process that ran them, and each greedy
    baseline's ``baseline_seconds`` (its candidates' solves, also summed over resumes).
    A run resumed in another process thus still reports what its training took (its
    ``wall_s`` counts only the last segment). For the same reason the history's
    per-iteration ``seconds`` are left out.

    Args:
        experiment: the experiment's name.
        config: the run's resolved config as plain dicts (stored as ``config``).
        methods: ``{name: {"learners": [row, ...], ...}}`` in the table's order.
    """
    training_s = {k: sum(h["seconds"] for h in hist) for k, hist in histories.items()
                  if hist and all(h.get("seconds") is not None for h in hist)}
    return {
        "experiment": experiment, "wall_s": time.perf_counter() - t_start,
        "training_s": {**training_s, **(baseline_seconds or {})},
        "methods": {k: {"learners": v["learners"]} for k, v in methods.items()},
        "consensus_max_pairwise_cost_distance": disagreement,
        "history": {k: [{**h, "seconds": None} for h in hist] for k, hist in histories.items()},
        "config": dict(config),
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


# The paper's Table 1 (grid world) and Table 2 (drones) metric columns.
TABLE1_COLUMNS = ("CR", "FPR", "FNR", "CVR", "RFD")
TABLE2_COLUMNS = ("FPR", "FNR", "CVR", "SR")
_FORMATS = {"FPR": (7, ".2f"), "FNR": (7, ".2f"), "CVR": (8, ".3f"), "RFD": (8, ".3f"),
            "SR": (7, ".2f"), "FNR_required": (8, ".2f"), "region_recall": (7, ".2f"),
            "region_precision": (7, ".2f"), "region_precision_determined": (8, ".2f"),
            "region_iou": (7, ".2f"), "obstacle_recall_required": (7, ".2f"),
            "obstacle_FPR": (7, ".2f"), "obstacle_FPR_determined": (8, ".2f"),
            "KB_sent": (9, ".1f")}
# The region scores (dicrl_torch.region): recall, precision (undetermined states counted
# as false / set apart) and IoU of the learned set as a classifier of states; the grid's
# recall over the required obstacle cells and FPR over the free cells.
_HEADERS = {"FNR_required": "FNR_req", "region_recall": "R_rec", "region_precision": "R_prec",
            "region_precision_determined": "R_prec*", "region_iou": "R_IoU",
            "obstacle_recall_required": "O_req", "obstacle_FPR": "O_FPR",
            "obstacle_FPR_determined": "O_FPR*", "KB_sent": "KB_sent"}
REGION_COLUMNS = ("region_recall", "region_precision", "region_precision_determined",
                  "region_iou")
# The grid's scores of (expert, cell) pairs and of moves (dicrl_torch.runs.grid_regions).
OBSTACLE_COLUMNS = ("obstacle_recall", "obstacle_recall_required", "obstacle_FPR",
                    "obstacle_FPR_determined", "move_recall", "move_FPR")


def column_header(key: str) -> str:
    """A row key as the printed table heads it (``region_recall`` -> ``R_rec``)."""
    return _HEADERS.get(key, key)


def print_table(methods: dict, columns: Sequence[str] = TABLE1_COLUMNS) -> None:
    """Print ``methods`` (``{name: {"D", "NATR", "learners": [row, ...]}}``) in the paper's
    layout: one line per learner, a metric that does not apply as N/A."""
    fmt = lambda x, f: "N/A" if x is None else format(x, f)  # noqa: E731
    head = f"{'':26s}{'D':>3s}{'NATR':>6s}"
    for c in columns:
        head += f"{'CR':>20s}" if c == "CR" else f"{column_header(c):>{_FORMATS[c][0]}s}"
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
