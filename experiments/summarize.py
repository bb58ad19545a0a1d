"""Mean ± std across the runs of a Hydra multirun (e.g. a seed sweep).

    .venv/bin/python experiments/train.py -m experiment=quick seed=0,1,2 hydra/launcher=joblib
    .venv/bin/python experiments/summarize.py multirun/quick/<date>

Reads every ``results.json`` below the given directory (one per run) and prints, for
each method row of the table (``D-ICRL 1`` … ``Experts (nominal)``), the mean ± std
across runs of CR (the per-run mean), SR, FPR, FNR, FNR_required, CVR, RFD and KB_sent (null where a
run lacks a value, e.g. SR on the grid or older runs without FNR_required; a column null in
every row is not printed); writes the same numbers to ``summary.json`` in that directory.
Runs of different experiments are refused.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

METRICS = ("CR_mean", "SR", "FPR", "FNR", "FNR_required", "CVR", "RFD", "KB_sent")


def load_runs(root: Path) -> list[dict]:
    """Every run's ``results.json`` under ``root``, sorted by path."""
    paths = sorted(root.rglob("results.json"))
    if not paths:
        raise ValueError(f"No results.json under {root}; give the multirun directory that "
                         f"Hydra printed (multirun/<name>/<date>).")
    runs = []
    for path in paths:
        try:
            runs.append({"path": str(path), **json.loads(path.read_text())})
        except json.JSONDecodeError as e:
            raise ValueError(f"{path} is not valid JSON ({e}); was the run interrupted? "
                             f"Rerun it or remove its directory.") from e
    names = {r["experiment"] for r in runs}
    if len(names) > 1:
        raise ValueError(f"Runs of different experiments {sorted(names)} under {root}; "
                         f"summarise one sweep at a time.")
    return runs


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for a single value)."""
    n = len(values)
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return mean, math.sqrt(var)


def summarize(runs: list[dict]) -> dict[str, dict[str, tuple[float, float] | None]]:
    """``{row label: {metric: (mean, std) or None}}`` in the table's row order."""
    rows: dict[str, list[dict]] = {}
    for run in runs:
        for method, m in run["methods"].items():
            learners = m["learners"]
            for j, row in enumerate(learners):
                label = f"{method} {j + 1}" if len(learners) > 1 else method
                rows.setdefault(label, []).append(row)
    out: dict[str, dict[str, tuple[float, float] | None]] = {}
    for label, rs in rows.items():
        out[label] = {}
        for k in METRICS:
            vals = [r.get(k) for r in rs]
            out[label][k] = None if any(v is None for v in vals) else mean_std(vals)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the multirun directory")
    args = parser.parse_args(argv)
    try:
        runs = load_runs(args.root)
    except ValueError as e:
        sys.exit(f"error: {e}")
    table = summarize(runs)
    print(f"{runs[0]['experiment']}: mean ± std over {len(runs)} runs")
    shown = [k for k in METRICS if any(cols[k] is not None for cols in table.values())]
    print(f"{'':24s}" + "".join(f"{k.removesuffix('_mean'):>18s}" for k in shown))
    for label, cols in table.items():
        cells = ["N/A" if cols[k] is None else f"{cols[k][0]:.3f} ± {cols[k][1]:.3f}"
                 for k in shown]
        print(f"{label:24s}" + "".join(f"{c:>18s}" for c in cells))
    (args.root / "summary.json").write_text(json.dumps(
        {"runs": [r["path"] for r in runs], "rows": table}, indent=1))


if __name__ == "__main__":
    main()
