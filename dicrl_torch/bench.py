"""Benchmarks: ``python -m dicrl_torch.bench solver --experts N [--grid G] ...``.

Prints one JSON line (docs/design.md §8)::

    {"pairs": int, "backward_sweep_s": float, "forward_sweep_s": float,
     "peak_rss_gb": float, "device": str, ...}

``backward_sweep_s`` / ``forward_sweep_s`` are the median seconds per time step over
``--repeat`` timed solves (after one warm-up solve, which also compiles kernels).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys

import torch

from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman


def _peak_rss_gb() -> float:
    # ru_maxrss is in KiB on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def bench_solver(*, experts: int, grid: int = 9, horizon: int = 10, repeat: int = 3,
                 device: str = "cpu", compile: bool | str = "auto", seed: int = 0) -> dict:
    """Time the factored solver on the nominal ``grid x grid`` game (the 9x9 case uses
    the paper's layout; obstacles do not change the learner's model)."""
    layout = GridLayout.scobee(experts) if grid == 9 else GridLayout.open_grid(grid, experts)
    model = TabularGridModel(layout=layout, horizon=horizon, gamma=0.99)
    solver = FactoredSoftBellman(model=model, device=device, compile=compile)
    rb, cb = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    g = torch.Generator().manual_seed(seed)
    reward = rb().weighted(rb.true_weights()) + cb().weighted(
        torch.rand(cb.dim, generator=g, dtype=torch.float64)).scale(-5.0)
    bwd, fwd = [], []
    for rep in range(repeat + 1):
        sol = solver.solve(reward, forward=True)
        if rep > 0:  # the first solve warms up (and compiles)
            bwd.append(sol.timings["backward_s"] / horizon)
            fwd.append(sol.timings["forward_s"] / horizon)
    occ_total = float(sol.state_occupancy.sum())
    dev = solver.device
    device_name = str(dev) if dev.type == "cpu" else torch.cuda.get_device_name(dev)
    expected = sum(model.gamma**t for t in range(horizon))
    return {
        "pairs": model.n_pairs,
        "backward_sweep_s": statistics.median(bwd),
        "forward_sweep_s": statistics.median(fwd),
        "peak_rss_gb": round(_peak_rss_gb(), 3),
        "device": device_name,
        "experts": experts, "grid": grid, "horizon": horizon, "repeat": repeat,
        "compiled": solver.use_compile, "threads": torch.get_num_threads(),
        "backward_all_s": [round(x, 4) for x in bwd],
        "forward_all_s": [round(x, 4) for x in fwd],
        "occupancy_mass_error": abs(occ_total - expected),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dicrl_torch.bench")
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("solver", help="time the factored soft-Bellman solver")
    p.add_argument("--experts", type=int, required=True, choices=(1, 2, 3))
    p.add_argument("--grid", type=int, default=9, help="side G of a nominal GxG grid")
    p.add_argument("--horizon", type=int, default=10, help="time steps per sweep")
    p.add_argument("--repeat", type=int, default=3, help="timed solves (median reported)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--compile", default="auto", choices=("auto", "on", "off"))
    args = parser.parse_args(argv)
    if args.grid < 2:
        parser.error("--grid must be >= 2")
    if args.horizon < 1 or args.repeat < 1:
        parser.error("--horizon and --repeat must be >= 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda requested but CUDA is not available")
    compile_ = {"auto": "auto", "on": True, "off": False}[args.compile]
    result = bench_solver(experts=args.experts, grid=args.grid, horizon=args.horizon,
                          repeat=args.repeat, device=args.device, compile=compile_)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
