"""A PNG of what TensorBoard's scalar dashboard shows for a training run.

    .venv/bin/python experiments/tb_snapshot.py outputs/quick/<date>
    .venv/bin/python experiments/tb_snapshot.py RUN_DIR --tags outer/multiplier eval/FPR \\
        --image eval/constraint_map --image-run learner0 --out docs/img/tensorboard_quick.png

Reads the event files under ``RUN_DIR/tb`` (one run per sub-directory: ``learner0`` …,
``c_icrl``, ``network``, baselines) with TensorBoard's ``EventAccumulator``; draws one panel
per scalar tag, x = step, one line per run, raw values (smoothing 0); ``--image`` adds the
last image of an image tag. Rendered from the event files, not a screenshot of the UI (the
title says so). Writes ``RUN_DIR/tensorboard_scalars.png`` by default.
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

# Tags that no run has (e.g. inner/ when the inner process is not logged) are skipped.
DEFAULT_TAGS = ("outer/multiplier", "outer/lga_norm", "eval/FPR", "eval/FNR", "eval/RFD",
                "eval/CR", "inner/dual_gradient_norm", "consensus/max_pairwise_cost_distance",
                "consensus/max_pairwise_eta_distance")
Series = tuple[np.ndarray, np.ndarray]  # (steps, values)


def load_runs(run_dir: str | Path) -> dict[str, EventAccumulator]:
    """One loaded accumulator per TensorBoard run (directory holding event files) under
    ``run_dir/tb``, named like TensorBoard names them: the path relative to ``tb``."""
    tb = Path(run_dir) / "tb"
    if not tb.is_dir():
        raise ValueError(f"{tb} does not exist; give the run directory that train.py printed "
                         f"(the one holding results.json and tb/).")
    dirs = sorted({p.parent for p in tb.rglob("events.out.tfevents.*")})
    if not dirs:
        raise ValueError(f"No TensorBoard event files under {tb}; was the run started with "
                         f"TensorBoard logging, and did it log at least one step?")
    runs = {}
    for d in dirs:
        # 0 = keep every scalar; images: a reservoir of 1 still keeps the latest one.
        acc = EventAccumulator(str(d), size_guidance={"scalars": 0, "images": 1})
        runs[d.relative_to(tb).as_posix()] = acc.Reload()
    return runs


def read_scalars(run_dir: str | Path) -> dict[str, dict[str, Series]]:
    """``{tag: {run: (steps, values)}}`` of every scalar in ``run_dir/tb``."""
    out: dict[str, dict[str, Series]] = {}
    for run, acc in load_runs(run_dir).items():
        for tag in acc.Tags()["scalars"]:
            events = acc.Scalars(tag)
            out.setdefault(tag, {})[run] = (np.array([e.step for e in events]),
                                            np.array([e.value for e in events]))
    return out


def last_image(run_dir: str | Path, tag: str, run: str | None = None
               ) -> tuple[str, int, np.ndarray]:
    """(run, step, RGB(A) array) of the latest ``tag`` image, of ``run`` or the first run
    (sorted by name) that has it."""
    runs = load_runs(run_dir)
    having = [name for name, acc in runs.items()
              if tag in acc.Tags()["images"] and run in (None, name)]
    if not having:
        available = sorted(f"{t} ({name})" for name, acc in runs.items()
                           for t in acc.Tags()["images"])
        raise ValueError(f"No run{'' if run is None else ' ' + run} has image tag {tag!r}; "
                         f"available: {available}.")
    event = runs[having[0]].Images(tag)[-1]
    return having[0], event.step, matplotlib.image.imread(io.BytesIO(event.encoded_image_string))


def render(run_dir: str | Path, tags: list[str] | None = None, image: str | None = None,
           image_run: str | None = None, out: str | Path | None = None) -> Path:
    """Draw the dashboard of ``run_dir`` and write it as a PNG; returns its path."""
    run_dir = Path(run_dir)
    scalars = read_scalars(run_dir)
    tags = tags or [t for t in DEFAULT_TAGS if t in scalars]
    missing = [t for t in tags if t not in scalars]
    if missing or not tags:  # a typo in --tags must not silently drop a panel
        raise ValueError(f"No run has scalar tag(s) {missing or list(DEFAULT_TAGS)}; pass "
                         f"--tags with some of the available ones: {sorted(scalars)}.")
    picture = last_image(run_dir, image, image_run) if image else None
    # One colour per run across every panel, as in TensorBoard's run selector.
    runs = sorted({r for t in tags for r in scalars[t]})
    colors = {run: f"C{i % 10}" for i, run in enumerate(runs)}
    n = len(tags) + (picture is not None)
    nrows = 1 if n <= 3 else 2 if n <= 8 else 3
    ncols = math.ceil(n / nrows)
    fig = Figure(figsize=(14, 8), dpi=100)
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, tag in zip(axes, tags, strict=False):
        for run, (steps, values) in sorted(scalars[tag].items()):
            # Sparse tags (eval/CR: a few steps) get markers so single points show.
            ax.plot(steps, values, color=colors[run], lw=1.4,
                    marker="o" if len(steps) < 10 else None, ms=3)
        ax.set_title(tag, loc="left", fontsize=10)
        ax.grid(True, color="#e0e0e0", lw=0.6)
        ax.tick_params(labelsize=8, length=2, colors="#555555")
        ax.set_xlabel("step", fontsize=8, color="#555555")
        ax.spines[["top", "right"]].set_visible(False)
    if picture is not None:
        name, step, img = picture
        ax = axes[len(tags)]
        ax.imshow(img)
        ax.set_title(f"{image} ({name}, step {step})", loc="left", fontsize=10)
        ax.axis("off")
    for ax in axes[n:]:
        ax.set_visible(False)
    # A shared legend below the panels, so it never covers a line.
    handles = [Line2D([], [], color=colors[r], lw=2, label=r) for r in runs]
    fig.legend(handles=handles, loc="lower center", ncol=len(runs), fontsize=9, frameon=False)
    fig.suptitle(f"TensorBoard scalars of {run_dir.resolve().name} "
                 f"(rendered from the event files in tb/)", fontsize=12)
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    out = Path(out) if out else run_dir / "tensorboard_scalars.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    canvas.print_png(str(out))
    return out


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--tags", nargs="+", help=f"scalar tags (default: those of {DEFAULT_TAGS} "
                                             f"that some run has)")
    p.add_argument("--image", help="image tag whose last image is an extra panel")
    p.add_argument("--image-run", help="run of --image (default: the first that has it)")
    p.add_argument("--out", type=Path, help="PNG path (default RUN_DIR/tensorboard_scalars.png)")
    a = p.parse_args(argv)
    try:
        out = render(a.run_dir, a.tags, a.image, a.image_run, a.out)
    except ValueError as e:
        sys.exit(f"error: {e}")
    print(out)
    return out


if __name__ == "__main__":
    main()
