"""Compare the D-learners of finished runs that differ only in their communicator:
bytes sent, learned sets, CR and CVR, against a reference run (docs/communication.md).

    .venv/bin/python experiments/studies/traffic.py REFERENCE_DIR RUN_DIR [RUN_DIR ...] \
        [--figure traffic.png]

Each directory holds a run's ``results.json``. Prints one JSON line per D-learner of each
run: its algorithm bytes sent, the reference's over its own (``fewer_bytes``), whether its
learned constraints are the reference learner's (``same_constraints``), and its CR and
CVR beside the reference's. ``--figure`` draws every run's learners' metrics against the
bytes they had sent (:func:`dicrl_torch.figures.metrics_against_bytes`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def d_icrl(run: Path) -> tuple[list[dict], list[dict]]:
    """(the D-ICRL rows, the D-ICRL history) of ``run``'s results.json."""
    res = json.loads((run / "results.json").read_text())
    rows = res["methods"]["D-ICRL"]["learners"]
    if any("traffic" not in r for r in rows):
        raise SystemExit(f"{run}: its rows hold no traffic (written before the "
                         f"communicators counted it); rerun it.")
    return rows, res["history"]["D-ICRL"]


def compare(reference: Path, run: Path) -> list[dict]:
    ref_rows, _ = d_icrl(reference)
    rows, _ = d_icrl(run)
    if len(rows) != len(ref_rows):
        raise SystemExit(f"{run} has {len(rows)} D-learners, {reference} {len(ref_rows)}.")
    out = []
    for v, (ref, row) in enumerate(zip(ref_rows, rows, strict=True)):
        sent, ref_sent = (r["traffic"]["algorithm_bytes_sent"] for r in (row, ref_rows[v]))
        out.append({
            "run": str(run), "learner": v + 1, "bytes_sent": sent,
            "reference_bytes_sent": ref_sent, "fewer_bytes": ref_sent / max(sent, 1),
            "same_constraints": sorted(row.get("constraints") or [])
            == sorted(ref.get("constraints") or []),
            "CR": row.get("CR_mean"), "reference_CR": ref.get("CR_mean"),
            "CR_ratio": (row["CR_mean"] / ref["CR_mean"]
                         if row.get("CR_mean") and ref.get("CR_mean") else None),
            "CVR": row.get("CVR"), "reference_CVR": ref.get("CVR"),
            "SR": row.get("SR"), "reference_SR": ref.get("SR")})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reference", type=Path)
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--figure", type=Path, default=None)
    args = parser.parse_args()
    for run in args.runs:
        for record in compare(args.reference, run):
            print(json.dumps(record))
    if args.figure is not None:
        from dicrl_torch.figures import metrics_against_bytes, save_png

        histories = {p.name: d_icrl(p)[1] for p in (args.reference, *args.runs)}
        save_png(args.figure, metrics_against_bytes(
            histories, title="each D-learner's metrics against the bytes it sent"))
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
