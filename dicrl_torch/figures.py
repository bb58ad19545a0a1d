"""The paper's Fig. 2 (§6.1) for a run: visitation heat maps and metric curves.

- :func:`visitation_heatmap`: where the experts go (:func:`state_visitation` of the
  demonstrations, or a solver's occupancy), with constraints as red crosses: the true
  ones (Fig. 2a) or a learner's learned ones (Fig. 2b).
- :func:`metric_curves`: CR, FPR, FNR, CVR and RFD against the outer iteration, one line
  per learner, the baselines and experts as horizontal reference lines (Fig. 2c-2g).
- :func:`cost_weight_curves` (not in the paper): every ω_c,j against the outer
  iteration, true constraints in red, with the threshold rule's line.
- :func:`metrics_against_bytes` (not in the paper): each learner's FPR, FNR, CR and CVR
  against the bytes it had sent, for one run or several compared.
- :func:`identifiability_map` (not in the paper): the true constraint cells coloured by
  their identifiability class (docs/design.md §6), optionally with a learned set as
  crosses; :func:`identifiability_legend` names the classes and the features without a
  cell.

Pure functions of arrays and plain dicts (the ``history`` and table rows of
``results.json``): no Hydra, no trainer. Every figure is drawn on a private Agg canvas,
never pyplot's global state (safe headless and in threads), and returned as an RGB
``uint8`` image ``[H, W, 3]``, which :func:`save_png` writes and a logger's ``image``
takes as is.
"""

from __future__ import annotations

import re
import textwrap
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from dicrl_torch.envs.grid import GridLayout
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.envs.parallel import agg_axes, axes_image

# (history key, table-row key, panel title): the panels of Fig. 2c-2g, in the paper's
# order. A history holds "CR" (the mean return of the evaluation episodes), the table
# row "CR_mean".
METRICS: tuple[tuple[str, str, str], ...] = (
    ("CR", "CR_mean", "(c) CR: cumulative true reward"),
    ("FPR", "FPR", "(d) FPR: false positive rate"),
    ("FNR", "FNR", "(e) FNR: false negative rate"),
    ("CVR", "CVR", "(f) CVR: constraint violation rate"),
    ("RFD", "RFD", "(g) RFD: reward function distance"),
)
# Recorded after every outer iteration; CR and CVR (rollouts, costly) only every few.
EVERY_ITERATION = ("FPR", "FNR", "RFD")
CURVES_FIGSIZE = (20.0, 5.0)  # inches; 1 x 5 panels and the legend below them
DPI = 80
_CELL_NAME = re.compile(r"(?:^|/)cell\((\d+),(\d+)\)$")


# ---------------------------------------------------------------------- heat maps
def state_visitation(states, n_cells: int, *, gamma: float | None = None) -> np.ndarray:
    """Per-cell visitation ``[S1]`` of demonstrations ``states [m, T+1, N]``.

    Args:
        states: integer cells of ``N`` experts over ``m`` trajectories
            (``Demonstrations.states``).
        n_cells: ``S1``.
        gamma: None (what the figures show): the fraction of the ``m * N`` expert
            trajectories that enter the cell at least once, in ``[0, 1]``; an expert that
            waits at its goal for most of the horizon then does not wash its path out of
            the colour scale. A number: the discounted number of the ``T`` decision steps
            spent in the cell, ``Σ_t γ^t 1[s_t = s]`` averaged over the expert
            trajectories, the empirical counterpart of a solver's occupancy,
            ``solution.local_occupancy.sum(2).mean(0)``.

    Raises:
        ValueError: ``states`` is not an integer ``[m, T+1, N]`` array of cells in
            ``[0, n_cells)``, or ``gamma`` is not in ``(0, 1]``.
    """
    s = np.asarray(states)
    if s.ndim != 3 or s.shape[0] == 0 or s.shape[1] < 2 or not np.issubdtype(s.dtype, np.integer):
        raise ValueError(f"states must be an integer array [m, T+1, N] with m >= 1 and "
                         f"T >= 1 (Demonstrations.states), got {s.dtype} {list(s.shape)}.")
    if s.min() < 0 or s.max() >= n_cells:
        raise ValueError(f"states hold cells outside [0, {n_cells}); pass the n_cells of the "
                         f"layout the demonstrations were recorded in.")
    m, _, n = s.shape
    if gamma is None:
        visited = np.zeros((m * n, n_cells), dtype=bool)
        rows = np.repeat(np.arange(m * n), s.shape[1])
        visited[rows, s.transpose(0, 2, 1).reshape(-1)] = True
        return visited.mean(0)
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must be None or in (0, 1], got {gamma!r}.")
    decisions = s[:, :-1]  # the T states an action is taken in, as in the occupancy
    weight = np.broadcast_to((gamma ** np.arange(decisions.shape[1]))[None, :, None],
                             decisions.shape)
    return np.bincount(decisions.reshape(-1), weights=weight.reshape(-1),
                       minlength=n_cells) / (m * n)


def constraint_cells(layout: GridLayout, names: Iterable[str],
                     region_cells: Mapping[str, Iterable[int]] | None = None) -> list[int]:
    """Cell indices of the cell-constraint features among ``names`` (``cell(x,y)``, or
    ``expert<i>/cell(x,y)`` in a per-expert basis), and every cell of a region feature
    named in ``region_cells`` (a cost basis' ``region_cells``); action and collision
    constraints, and features of a basis without cells, have no cell and are left out."""
    cells = []
    region_cells = region_cells or {}
    for name in names:
        if name in region_cells:
            cells.extend(region_cells[name])
        elif match := _CELL_NAME.search(name):
            x, y = int(match[1]), int(match[2])
            if not (0 <= x < layout.size and 0 <= y < layout.size):
                raise ValueError(f"constraint {name!r} lies outside the {layout.size}x"
                                 f"{layout.size} grid; pass the layout it was learned on.")
            cells.append(layout.cell((x, y)))
    return sorted(set(cells))


def obstacle_cells(layout: GridLayout) -> list[int]:
    """The true cell constraints of ``layout`` (its obstacles), as cell indices."""
    return sorted(layout.cell(c) for c in layout.obstacles)


def visitation_heatmap(layout: GridLayout, visitation, *,
                       constraint_cells: Iterable[int] = (), title: str = "") -> np.ndarray:
    """The grid coloured by ``visitation`` ``[S1]`` (e.g. :func:`state_visitation`),
    true obstacles hatched, starts as circles, goals as stars, ``constraint_cells`` as
    red crosses: the true constraints (Fig. 2a) or learned ones (Fig. 2b).

    Returns:
        The RGB image ``[H, W, 3]`` uint8.

    Raises:
        ValueError: ``visitation`` is not ``[S1]`` finite values >= 0.
    """
    v = np.asarray(visitation, dtype=np.float64)
    if v.shape != (layout.n_cells,) or not np.all(np.isfinite(v)) or (v < 0).any():
        raise ValueError(f"visitation must hold one finite value >= 0 per cell, shape "
                         f"[{layout.n_cells}]; got shape {list(v.shape)}. Compute it with "
                         f"state_visitation(demos.states, layout.n_cells).")
    return render_grid(layout, heat=v, constraint_cells=constraint_cells, title=title)


def side_by_side(images: Sequence[np.ndarray]) -> np.ndarray:
    """Images ``[H_k, W_k, 3]`` in one row (shorter ones padded with white below)."""
    if not images:
        raise ValueError("side_by_side needs at least one image.")
    h = max(im.shape[0] for im in images)
    return np.concatenate([np.pad(im, ((0, h - im.shape[0]), (0, 0), (0, 0)),
                                  constant_values=255) for im in images], axis=1)


def tiled(images: Sequence[np.ndarray], max_width: int = 1400) -> np.ndarray:
    """Images in rows of :func:`side_by_side`, a new row where the next image would make
    one wider than ``max_width`` pixels; rows stacked, narrower ones padded white right."""
    if not images:
        raise ValueError("tiled needs at least one image.")
    rows: list[list[np.ndarray]] = [[]]
    for im in images:
        if rows[-1] and sum(i.shape[1] for i in rows[-1]) + im.shape[1] > max_width:
            rows.append([])
        rows[-1].append(im)
    strips = [side_by_side(r) for r in rows]
    w = max(s.shape[1] for s in strips)
    return np.concatenate([np.pad(s, ((0, 0), (0, w - s.shape[1]), (0, 0)),
                                  constant_values=255) for s in strips], axis=0)


# ---------------------------------------------------------------------- identifiability
IDENTIFIABILITY_CLASSES = ("demonstrated", "required", "undetermined")
# Okabe-Ito colours, apart from the experts' (blue, orange, green) and the crosses' red;
# "mixed": a cell whose features (one per expert in a per-expert basis) differ in class.
CLASS_COLOURS = {"demonstrated": "#CC79A7", "required": "#F0E442",
                 "undetermined": "#56B4E9", "mixed": "#BBBBBB"}


def identifiability_cells(layout: GridLayout, classes: Mapping[str, Iterable[str]],
                          region_cells: Mapping[str, Iterable[int]] | None = None
                          ) -> tuple[dict[int, str], dict[str, str]]:
    """Where the classified features lie.

    Args:
        classes: class -> feature names, for the classes of
            :data:`IDENTIFIABILITY_CLASSES` (``Identifiability.as_dict()``, the
            ``identifiability`` record of ``results.json``); other keys are ignored.
        region_cells: a cost basis' ``region_cells`` (see :func:`constraint_cells`).

    Returns:
        ``cell -> class`` (``"mixed"`` where the features on a cell differ in class) and
        ``name -> class`` of the features without a cell (actions, collision), in the
        order given.
    """
    on_cell: dict[int, set[str]] = {}
    off_grid: dict[str, str] = {}
    for cls in IDENTIFIABILITY_CLASSES:
        for name in classes.get(cls, ()):
            cells = constraint_cells(layout, [name], region_cells)
            for c in cells:
                on_cell.setdefault(c, set()).add(cls)
            if not cells:
                off_grid[name] = cls
    return ({c: next(iter(k)) if len(k) == 1 else "mixed" for c, k in sorted(on_cell.items())},
            off_grid)


def identifiability_map(layout: GridLayout, cell_classes: Mapping[int, str], *,
                        constraint_cells: Iterable[int] = (), title: str = "") -> np.ndarray:
    """:func:`render_grid` (obstacles, starts, goals, ``constraint_cells`` as red crosses)
    with each cell of ``cell_classes`` (:func:`identifiability_cells`) filled in its
    :data:`CLASS_COLOURS`, under the markers, crosses and grid lines.

    Returns:
        The RGB image ``[H, W, 3]`` uint8, the size of :func:`render_grid`'s.
    """
    unknown = sorted(set(cell_classes.values()) - set(CLASS_COLOURS))
    if unknown:
        raise ValueError(f"unknown identifiability classes {unknown}; use "
                         f"{list(CLASS_COLOURS)}.")
    return render_grid(layout, constraint_cells=constraint_cells, title=title,
                       cell_colours={c: CLASS_COLOURS[cls] for c, cls in cell_classes.items()})


def identifiability_legend(off_grid: Mapping[str, str], *, mixed: bool = False,
                           height: int = 320, max_listed: int = 10) -> np.ndarray:
    """A legend panel ``[height, W, 3]``: the class colours (and ``"mixed"`` if
    ``mixed``) and the features without a cell with their class (``off_grid``, from
    :func:`identifiability_cells`; at most ``max_listed`` named)."""
    fig = Figure(figsize=(2.6, height / DPI), dpi=DPI)
    canvas = FigureCanvasAgg(fig)
    shown = [*IDENTIFIABILITY_CLASSES, *(["mixed"] if mixed else [])]
    labels = {"mixed": "mixed (per-expert\nfeatures differ)"}
    legend = fig.legend([Patch(fc=CLASS_COLOURS[c], ec="0.3") for c in shown] +
                        [Line2D([], [], ls="", marker="x", ms=9, mew=2, color="red")],
                        [labels.get(c, c) for c in shown] + ["learned constraint"],
                        loc="upper left", title="true constraints", fontsize=9,
                        title_fontsize=9, frameon=False)
    lines = [f"{name}: {cls}" for name, cls in list(off_grid.items())[:max_listed]]
    if len(off_grid) > max_listed:
        lines.append(f"and {len(off_grid) - max_listed} more")
    canvas.draw()
    below = legend.get_window_extent().transformed(fig.transFigure.inverted()).y0
    fig.text(0.05, below - 0.04, "true constraints not on a cell:\n" +
             ("\n".join(lines) or "none"), va="top", fontsize=8)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


# The longest line of a render_grid title (8 pt, centred over the axes of a 3.6 in wide
# figure): a line of about 60 characters of feature names reaches the figure's edges.
_TITLE_CHARS = 45
_NBSP = "\N{NO-BREAK SPACE}"  # keeps a feature name such as "action NE" on one line


def _wrap(text: str) -> list[str]:
    """``text`` wrapped at :data:`_TITLE_CHARS`, broken only at (breaking) spaces."""
    lines = textwrap.wrap(text, _TITLE_CHARS, break_long_words=False, break_on_hyphens=False)
    return [line.replace(_NBSP, " ") for line in lines] or [""]


def _listing(prefix: str, names: Sequence[str], max_lines: int = 2) -> list[str]:
    """``prefix`` and as many of ``names`` as fit in ``max_lines`` wrapped title lines, the
    rest counted (``+2 more``); ``prefix none`` if there are no names."""
    if not names:
        return _wrap(f"{prefix} none")
    for k in range(len(names), 0, -1):
        shown = [n.replace(" ", _NBSP) for n in names[:k]]
        if k < len(names):
            shown.append(f"+{len(names) - k}{_NBSP}more")
        lines = _wrap(f"{prefix} " + ", ".join(shown))
        if len(lines) <= max_lines:
            return lines
    return _wrap(f"{prefix} +{len(names)}{_NBSP}more")


def _rate(value) -> str:
    return "N/A" if value is None else format(value, ".2f")


def identifiability_figure(layout: GridLayout, classes: Mapping[str, Iterable[str]],
                           rows: Mapping[str, Mapping], *,
                           region_cells: Mapping[str, Iterable[int]] | None = None,
                           max_width: int = 1400) -> np.ndarray:
    """The true constraints by identifiability class (docs/design.md §6) beside each
    learned set: first the classes and their legend, then one panel per learned row,
    its constraints as crosses and its FPR / FNR / FNR_required in the title; rows
    wrap at ``max_width`` pixels (:func:`tiled`).

    Args:
        classes: class -> true constraint names (``Identifiability.as_dict()``).
        rows: panel label -> table row with ``constraints`` (feature names), ``FPR``,
            ``FNR`` and ``FNR_required`` (None or missing: N/A).
        region_cells: the cost basis' ``region_cells``.
    """
    cells, off_grid = identifiability_cells(layout, classes, region_cells)
    counts = ", ".join(f"{len(list(classes.get(c, ())))} {c}" for c in IDENTIFIABILITY_CLASSES)
    title = [*_wrap("True constraints by identifiability class"), *_wrap(counts)]
    panels = [identifiability_map(layout, cells, title="\n".join(title)),
              identifiability_legend(off_grid, mixed="mixed" in cells.values())]
    true_class = {n: c for c in IDENTIFIABILITY_CLASSES for n in classes.get(c, ())}
    for label, row in rows.items():
        learned = list(row["constraints"])
        # learned features without a cell (their classes are in the legend), false ones
        # marked; at most two lines of the title
        off = [n if n in true_class else f"{n} (false)" for n in learned
               if not constraint_cells(layout, [n], region_cells)]
        lines = _listing(f"{len(learned)} learned (x); not on a cell:", off)
        rates = ", ".join(f"{k} {_rate(row.get(k))}" for k in ("FPR", "FNR", "FNR_required"))
        panels.append(identifiability_map(
            layout, cells, constraint_cells=constraint_cells(layout, learned, region_cells),
            title="\n".join([*_wrap(label), *_wrap(rates), *lines])))
    return tiled(panels, max_width)


# ---------------------------------------------------------------------- metric curves
def _learner_series(method: str, history: Sequence[Mapping]) -> tuple[np.ndarray, dict]:
    """``x`` ``[n]`` (outer iterations done, 1-based) and per metric ``[n, L]`` values
    (NaN where not evaluated) of a method's history.

    Raises:
        ValueError: naming the method, the outer iteration and the fix.
    """
    if not history:
        raise ValueError(f"the history of {method!r} is empty: it has no outer iteration to "
                         f"plot; leave the method out.")
    n_learners, first = None, None
    x, values = [], {key: [] for key, _, _ in METRICS}
    for j, entry in enumerate(history):
        if "outer_iteration" not in entry:
            raise ValueError(
                f"the history of {method!r} has no 'outer_iteration' in entry {j}: it is not "
                f"a bi-level method's (a greedy baseline's history counts constraints added); "
                f"pass a baseline's final table row in baselines= instead.")
        n = int(entry["outer_iteration"])
        if x and n <= x[-1] - 1:
            raise ValueError(f"the history of {method!r} goes back from outer iteration "
                             f"{x[-1] - 1} to {n}; pass the history of one run, in order.")
        x.append(n + 1)
        for key, _, _ in METRICS:
            v = entry.get(key)
            if v is None:
                if key in EVERY_ITERATION:
                    raise ValueError(
                        f"the history of {method!r} has no {key!r} at outer iteration {n}: "
                        f"it was written before experiments/train.py recorded the metrics "
                        f"of every outer iteration; rerun the experiment.")
                values[key].append(None)
                continue
            if not isinstance(v, list | tuple):
                raise ValueError(f"the history of {method!r} holds {key}={v!r} at outer "
                                 f"iteration {n}; it must be a list, one value per learner.")
            if n_learners is None:
                n_learners, first = len(v), (n, key)
            elif len(v) != n_learners:
                raise ValueError(
                    f"the history of {method!r} has mismatched lengths: outer iteration {n} "
                    f"holds {len(v)} {key!r} values, outer iteration {first[0]} "
                    f"{n_learners} {first[1]!r} values; every per-learner list needs one "
                    f"value per learner. Pass the history of one run as results.json holds "
                    f"it (a distributed run's learners merged by merge_learner_rows).")
            values[key].append(v)
    if not n_learners:
        raise ValueError(f"the history of {method!r} holds no learner's values; leave the "
                         f"method out.")
    nan = [np.nan] * n_learners
    return np.asarray(x), {k: np.array([nan if v is None else v for v in vs], dtype=float)
                           for k, vs in values.items()}


def metric_curves(histories: Mapping[str, Sequence[Mapping]], *,
                  final_rows: Mapping[str, Sequence[Mapping]] | None = None,
                  baselines: Mapping[str, Mapping] | None = None,
                  experts: Mapping[str, Mapping] | None = None,
                  title: str = "") -> np.ndarray:
    """Fig. 2c-2g: CR, FPR, FNR, CVR and RFD against the outer iteration, 1 x 5 panels.

    Args:
        histories: bi-level method (``"D-ICRL"``, ``"C-ICRL"``) -> its ``results.json``
            history: one entry per outer iteration with ``outer_iteration`` and
            per-learner lists ``FPR``, ``FNR``, ``RFD`` (every iteration) and ``CR``,
            ``CVR`` (where evaluated). One line per learner: ``"<method> learner <v>"``,
            or the method's name when it has one learner.
        final_rows: method -> its table rows (one per learner; ``CR_mean``, ``FPR``, ...),
            drawn as hollow diamonds at the last iteration: the table's values, after
            pruning, where the curves show the constraints before it.
        baselines: name -> final table row of a method that is not bi-level (the greedy
            baselines): a dotted horizontal line at each metric it has.
        experts: name -> table row (the expert rows): a dashed horizontal line at each
            metric it has (None: not applicable, e.g. an expert's FPR).
        title: the figure's title.

    Returns:
        The RGB image ``[H, W, 3]`` uint8, ``H, W = CURVES_FIGSIZE[::-1] * DPI``.

    Raises:
        ValueError: no history, or one that is not a bi-level method's, lacks a metric,
            or holds per-learner lists of mismatched lengths.
    """
    if not histories:
        raise ValueError("metric_curves needs the history of at least one bi-level method "
                         "(e.g. results.json's history['D-ICRL']).")
    series = {method: _learner_series(method, h) for method, h in histories.items()}
    fig = Figure(figsize=CURVES_FIGSIZE, dpi=DPI, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(METRICS))
    colours = iter(f"C{k}" for k in range(1000))
    lines = []  # (method, learner, label, colour, line width)
    for method, (_, values) in series.items():
        n_learners = values["FPR"].shape[1]
        for v in range(n_learners):
            label = f"{method} learner {v + 1}" if n_learners > 1 else method
            lines.append((method, v, label, next(colours), 1.4 if n_learners > 1 else 2.2))
    references = [(name, row, ":", f"{name} (final)", next(colours))
                  for name, row in (baselines or {}).items()]
    references += [(name, row, "--", name, next(colours)) for name, row in (experts or {}).items()]
    last_x = max(x[-1] for x, _ in series.values())
    for ax, (key, row_key, panel) in zip(axes, METRICS, strict=True):
        for method, v, label, colour, lw in lines:
            x, values = series[method]
            y = values[key][:, v]
            shown = ~np.isnan(y)  # CR and CVR: only the evaluated iterations
            sparse = not shown.all()
            ax.plot(x[shown], y[shown], "o-" if sparse else "-", ms=4, color=colour,
                    label=label, lw=lw)
            rows = (final_rows or {}).get(method)
            if rows is not None and v < len(rows) and rows[v].get(row_key) is not None:
                ax.plot([x[-1]], [rows[v][row_key]], "D", ms=8, mfc="none", mec=colour,
                        mew=1.5, zorder=4)
        for _, row, style, label, colour in references:
            if row.get(row_key) is not None:
                ax.axhline(row[row_key], ls=style, lw=1.5, color=colour, label=label)
        ax.set_title(panel, fontsize=11)
        ax.set_xlabel("outer iteration")
        ax.set_ylabel(key)
        ax.set_xlim(0.5, last_x + 0.5)
        if key in ("FPR", "FNR"):
            ax.set_ylim(-0.03, 1.03)  # rates: the full range, so that panels compare
        ax.grid(alpha=0.3)
    extra = {"table value (after pruning)": Line2D([], [], ls="", marker="D", ms=8, mfc="none",
                                                   mec="0.2", mew=1.5)} if final_rows else {}
    return _legend_and_render(fig, canvas, axes, title, extra=extra, ncol=6, fontsize=10)


BYTES_METRICS = (("FPR", "FPR"), ("FNR", "FNR"), ("CR", "CR"), ("CVR", "CVR"))


def metrics_against_bytes(histories: Mapping[str, Sequence[Mapping]], *,
                          title: str = "") -> np.ndarray:
    """Each learner's FPR, FNR, CR and CVR against the kilobytes it had sent (the
    algorithm's rounds), 1 x 4 panels: what a setting of the communicator buys.

    Args:
        histories: a run's label -> its D-ICRL history (``results.json``'s
            ``history["D-ICRL"]``), whose entries hold per-learner ``bytes_sent`` and the
            metrics (CR and CVR where evaluated). One line per learner; several runs (e.g.
            the exact exchange and a compressed one) share the panels, a colour each.

    Returns:
        The RGB image ``[H, W, 3]`` uint8.

    Raises:
        ValueError: no history, or one without ``bytes_sent``.
    """
    if not histories:
        raise ValueError("metrics_against_bytes needs at least one D-ICRL history.")
    fig = Figure(figsize=(16.0, 4.6), dpi=DPI, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(BYTES_METRICS))
    styles = ("-", "--", ":", "-.")
    for r, (label, history) in enumerate(histories.items()):
        if not history or any(h.get("bytes_sent") is None for h in history):
            raise ValueError(f"the history of {label!r} has no 'bytes_sent': it was written "
                             f"before the communicators counted their traffic; rerun it.")
        kb = np.array([h["bytes_sent"] for h in history], dtype=float) / 1000  # [n, L]
        for ax, (key, panel) in zip(axes, BYTES_METRICS, strict=True):
            values = np.array([[np.nan] * kb.shape[1] if h.get(key) is None else h[key]
                               for h in history], dtype=float)
            for v in range(kb.shape[1]):
                shown = ~np.isnan(values[:, v])
                ax.plot(kb[shown, v], values[shown, v], styles[r % len(styles)],
                        marker="o" if not shown.all() else None, ms=3, color=f"C{v}",
                        label=f"{label}, learner {v + 1}")
            ax.set_title(panel, fontsize=11)
            ax.set_xlabel("KB sent (algorithm rounds)")
            ax.set_xscale("log")  # runs that differ tenfold in bytes share the axis
            if key in ("FPR", "FNR"):
                ax.set_ylim(-0.03, 1.03)
            ax.grid(alpha=0.3)
    return _legend_and_render(fig, canvas, axes, title, ncol=4, fontsize=9)


def _legend_and_render(fig, canvas, axes, title: str, *, extra: Mapping | None = None,
                       ncol: int, fontsize: int) -> np.ndarray:
    """One legend below all panels (each label once, then ``extra`` handles), the title,
    and the drawn figure as RGB ``[H, W, 3]`` uint8."""
    handles = {}
    for ax in axes:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, h)
    handles.update(extra or {})
    fig.legend(handles.values(), handles.keys(), loc="outside lower center",
               ncol=min(len(handles), ncol), fontsize=fontsize, frameon=False)
    if title:
        fig.suptitle(title, fontsize=12)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def cost_weight_curves(histories: Mapping[str, Sequence[Mapping]], *,
                       true: Sequence[bool] | np.ndarray | None = None,
                       threshold: float | None = None, title: str = "") -> np.ndarray:
    """Every cost weight ω_c,j against the outer iteration, one panel per learner: the
    true constraints' in red, the other features' in grey, the threshold dashed. Shows
    how far the learned set is from the threshold rule's decision (a true feature just
    under it, a false one just over) and which iteration set each weight.

    Args:
        histories: method -> its ``results.json`` history, whose entries hold
            ``outer_iteration`` and ``cost_weights`` (``[L][l_c]``: each learner's ω_c
            after the iteration). Methods without ``cost_weights`` are left out.
        true: ``[l_c]`` bool, the true constraint features (None: every line grey).
        threshold: the threshold rule's ``ω_c,j >= threshold`` (None: no line).
        title: the figure's title.

    Returns:
        The RGB image ``[H, W, 3]`` uint8.

    Raises:
        ValueError: no method holds ``cost_weights``, or the widths disagree with
            ``true``.
    """
    panels = []  # (label, x [n], weights [n, l_c])
    for method, history in histories.items():
        rows = [h for h in history if h.get("cost_weights") is not None]
        if not rows:
            continue
        x = np.array([int(h["outer_iteration"]) + 1 for h in rows])
        w = np.array([h["cost_weights"] for h in rows], dtype=float)  # [n, L, l_c]
        if w.ndim != 3:
            raise ValueError(f"the history of {method!r} holds cost_weights of shape "
                             f"{list(w.shape[1:])} per entry; it must be [learners][features].")
        for v in range(w.shape[1]):
            label = f"{method} learner {v + 1}" if w.shape[1] > 1 else method
            panels.append((label, x, w[:, v]))  # ω_c(0) is not in the history
    if not panels:
        raise ValueError("cost_weight_curves needs a history whose entries hold "
                         "'cost_weights' (DICRL.outer_step writes them); rerun the "
                         "experiment.")
    width = panels[0][2].shape[1]
    true = np.zeros(width, bool) if true is None else np.asarray(true, dtype=bool)
    if true.shape != (width,):
        raise ValueError(f"true has {true.shape} entries but the histories hold {width} "
                         f"cost weights; pass the ground truth of this cost basis.")
    fig = Figure(figsize=(4.2 * len(panels), 3.6), dpi=DPI, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharey=True))
    for ax, (label, x, w) in zip(axes, panels, strict=True):
        dot = "." if len(x) == 1 else None  # one iteration: a point, not a line
        for j in np.flatnonzero(~true):  # the others first: the true lines stay on top
            ax.plot(x, w[:, j], color="0.6", lw=0.8, alpha=0.7, marker=dot)
        for j in np.flatnonzero(true):
            ax.plot(x, w[:, j], color="C3", lw=1.6, marker=dot)
        if threshold is not None:
            ax.axhline(threshold, color="k", ls="--", lw=1.0)
        ax.set_title(label, fontsize=11)
        ax.set_xlabel("outer iteration")
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("ω_c")
    handles = [Line2D([], [], color="0.6", lw=0.8, label="other feature")]
    if true.any():
        handles.insert(0, Line2D([], [], color="C3", lw=1.6, label="true constraint"))
    if threshold is not None:
        handles.append(Line2D([], [], color="k", ls="--", lw=1.0,
                              label=f"threshold {threshold:g}"))
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=10,
               frameon=False)
    if title:
        fig.suptitle(title, fontsize=12)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an RGB ``[H, W, 3]`` uint8 image as a PNG; returns the path."""
    import matplotlib.image

    path = Path(path)
    matplotlib.image.imsave(path, image)
    return path

def feature_strip(learned: np.ndarray, true: np.ndarray | None, *, title: str = ""
                  ) -> np.ndarray:
    """``[l]`` learned (filled red) and true (outlined black) features as one strip of
    squares, wrapped every 40, as an ``H x W x 3`` uint8 image."""
    from matplotlib.patches import Rectangle

    learned = np.asarray(learned, dtype=bool)
    width = min(40, len(learned))
    rows = -(-len(learned) // width)
    ax = agg_axes((max(3.0, 0.15 * width + 1), 0.2 * rows + 1.2))
    for j in range(len(learned)):
        x, y = j % width, -(j // width)
        ax.add_patch(Rectangle((x, y), 0.9, 0.9, color="red" if learned[j] else "0.9"))
        if true is not None and true[j]:
            ax.add_patch(Rectangle((x, y), 0.9, 0.9, fill=False, ec="k", lw=1.2))
    ax.set_xlim(-0.2, width)
    ax.set_ylim(-rows + 0.8, 1.1)
    ax.set_axis_off()
    return axes_image(ax, title)
