"""Foundation demo: experts, demonstrations and the experts' rows of Table 1.

    python experiments/demo_foundation.py [env.layout.n_experts=3] [seed=1] ...

Writes ``results.json`` (docs/design.md §8 layout, expert rows only), the demonstrations
(``demos.npz`` and one shard per learner), visitation heat maps (PNG) and the
learners' local estimates into the Hydra run directory, and prints the table.
This is the only place besides the other entry points that reads a config.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import numpy as np
import torch
from common import build_grid
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from tqdm.auto import tqdm

from dicrl_torch.demos import partition_demonstrations, save_demonstrations
from dicrl_torch.demos.features import local_estimates
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.io import write_json
from dicrl_torch.metrics import rollout_true_cmg
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories


def visitation(states: np.ndarray, n_cells: int) -> np.ndarray:
    """``[S1]`` fraction of (time, expert) visits per cell."""
    counts = np.bincount(states.reshape(-1), minlength=n_cells).astype(float)
    return counts / counts.sum()


@hydra.main(config_path="../configs", config_name="demo", version_base="1.3")
def main(cfg: DictConfig) -> None:
    t_start = time.perf_counter()
    out = Path(HydraConfig.get().runtime.output_dir)
    grid = build_grid(cfg)
    layout, model, solver = grid.layout, grid.model, grid.solver
    reward_basis, cost_basis = grid.reward_basis, grid.cost_basis
    w_true, reward_table = grid.true_reward_weights, grid.true_reward_table()
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    print(f"{layout.n_experts} experts on {layout.size}x{layout.size}: "
          f"{model.n_pairs:,} state-action pairs")

    rows, figures = {}, {}
    for name, constrained in tqdm([("Experts (ground truth)", True),
                                   ("Experts (nominal)", False)], desc="experts"):
        sol = expert_solution(solver=solver, reward_features=reward_basis(),
                              reward_weights=w_true, constrained=constrained,
                              temperature=cfg.expert_temperature)
        ev = rollout_true_cmg(policy=sol.policy_at, model=model, layout=layout,
                              reward_table=reward_table, n_episodes=cfg.eval_episodes, rng=gen)
        rows[name] = {"learners": [{"CR_mean": ev.cr_mean, "CR_std": ev.cr_std, "FPR": None,
                                    "FNR": None, "CVR": ev.cvr, "RFD": 0.0, "SR": None}]}
        figures[name] = visitation(ev.cells, layout.n_cells)
        if constrained:
            demos = sample_trajectories(sol, cfg.n_demonstrations, rng)

    save_demonstrations(out / "demos.npz", demos)
    shards = partition_demonstrations(demos, list(cfg.split), rng=rng)
    estimates = {}
    for v, shard in enumerate(shards):
        save_demonstrations(out / f"demos_learner{v}.npz", shard)
        estimates[f"learner{v}"] = {
            "m": shard.n_trajectories,
            "mu_r_hat": local_estimates(reward_basis(), shard, model.gamma).tolist(),
            "cost_accrual_nonzero": int(
                (local_estimates(cost_basis(), shard, model.gamma) > 0).sum()),
        }
    write_json(out / "local_estimates.json", estimates)

    true_cells = [layout.cell(c) for c in layout.obstacles]
    for name, heat in figures.items():
        # sqrt: experts spend most steps at their goals; the paths would not show
        img = render_grid(layout, heat=np.sqrt(heat), constraint_cells=true_cells,
                          title=f"{name}: √visitation, true CMG")
        fname = out / ("visitation_" + name.split("(")[1].rstrip(")").replace(" ", "_") + ".png")
        import matplotlib.image

        matplotlib.image.imsave(fname, img)

    results = {"experiment": "demo_foundation", "wall_s": time.perf_counter() - t_start,
               "methods": rows}
    write_json(out / "results.json", results)
    print(f"\n{'':26s}{'CR':>20s}{'CVR':>8s}")
    for name, row in rows.items():
        r = row["learners"][0]
        print(f"{name:26s}{r['CR_mean']:12.2f} ± {r['CR_std']:6.2f}{r['CVR']:8.3f}")
    print(f"\n{len(shards)} learners hold {[s.n_trajectories for s in shards]} demonstrations")
    print(f"results, demonstrations and figures in {out.resolve()}")


if __name__ == "__main__":
    main()
