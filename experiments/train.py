"""Train D-ICRL (and C-ICRL) on the grid world and report the paper's table.

    python experiments/train.py experiment=quick [seed=1] [graph=ring] [features/cost=per_expert]

Writes into the Hydra run directory: ``results.json`` (DESIGN §8), TensorBoard runs
(``tb/learner<v>``, ``tb/c_icrl``, ``tb/network``), learned-constraint maps (PNG) and
the demonstrations; prints the results table. This is one of the only places that
read a config: everything below is built here and handed to the library.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.algos.dicrl import DICRL
from dicrl_torch.demos import partition_demonstrations, save_demonstrations
from dicrl_torch.demos.experts import expert_solution, sample_trajectories
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.metrics import (
    false_negative_rate,
    false_positive_rate,
    learned_constraints,
    reward_function_distance,
    rollout_true_cmg,
)


def build(cfg, **objects):
    """Instantiate ``cfg`` with built objects as keyword arguments."""
    return instantiate(cfg, _partial_=True)(**objects)


def evaluate(policy, ctx) -> dict:
    ev = rollout_true_cmg(policy=policy, model=ctx["model"], layout=ctx["layout"],
                          reward_table=ctx["reward_table"], n_episodes=ctx["episodes"],
                          rng=ctx["rng"])
    return {"CR_mean": ev.cr_mean, "CR_std": ev.cr_std, "CVR": ev.cvr}


def learner_row(trainer: DICRL, i: int, ctx, threshold: float,
                prune_min_gain: float | None) -> dict:
    raw = learned_constraints(trainer.state.cost_weights[i], threshold)
    extra = {"FPR_before_pruning": false_positive_rate(raw, ctx["true"]),
             "FNR_before_pruning": false_negative_rate(raw, ctx["true"])}
    if prune_min_gain is not None:
        # Pruned constraints change the likelihood by < min_gain: the policy is the same.
        cw, pruned = trainer.prune_constraints(i, threshold, prune_min_gain, progress=True)
        trainer.state.cost_weights[i] = cw
        extra["pruned"] = len(pruned)
    learned = learned_constraints(trainer.state.cost_weights[i], threshold)
    row = evaluate(trainer.policy(i).policy_at, ctx)
    row.update(extra)
    row.update(FPR=false_positive_rate(learned, ctx["true"]),
               FNR=false_negative_rate(learned, ctx["true"]),
               RFD=reward_function_distance(trainer.state.eta_bar[i, :-1], ctx["w_true"]),
               SR=None, multiplier=float(trainer.state.eta_bar[i, -1]),
               n_learned=int(learned.sum()))
    return row


def constraint_map(layout, cost_basis, cost_weights, threshold, title):
    """PNG-ready map of learned cell constraints (cell features named ``cell(x,y)``)."""
    cells = [layout.cell(tuple(int(c) for c in name[name.index("(") + 1:-1].split(",")))
             for name, w in zip(cost_basis.names, cost_weights.tolist(), strict=True)
             if name.endswith(")") and "cell(" in name and w >= threshold]
    true_cells = [layout.cell(c) for c in layout.obstacles]
    heat = np.zeros(layout.n_cells)
    heat[true_cells] = 1.0
    return render_grid(layout, heat=heat, constraint_cells=cells, title=title)


def print_table(methods: dict) -> None:
    head = f"{'':26s}{'D':>3s}{'NATR':>6s}{'CR':>20s}{'FPR':>7s}{'FNR':>7s}{'CVR':>8s}{'RFD':>8s}"
    print(head)
    fmt = lambda x, f: "N/A" if x is None else format(x, f)  # noqa: E731
    for name, m in methods.items():
        for j, r in enumerate(m["learners"]):
            label = f"{name} {j + 1}" if len(m["learners"]) > 1 else name
            d, natr = m.get("D", "N/A"), m.get("NATR", "N/A")
            print(f"{label:26s}{d:>3s}{natr:>6s}{r['CR_mean']:11.2f} ± {r['CR_std']:6.2f}"
                  f"{fmt(r['FPR'], '.2f'):>7s}{fmt(r['FNR'], '.2f'):>7s}"
                  f"{r['CVR']:8.3f}{fmt(r['RFD'], '.3f'):>8s}")


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    t_start = time.perf_counter()
    out = Path(HydraConfig.get().runtime.output_dir)
    torch.set_num_threads(int(os.environ.get("DICRL_THREADS", torch.get_num_threads())))
    layout = instantiate(cfg.env.layout)
    model = build(cfg.env.model, layout=layout)
    solver = build(cfg.solver, model=model)
    reward_basis = build(cfg.features.reward, model=model)
    cost_basis = build(cfg.features.cost, model=model)
    logger = instantiate(cfg.logger, **({"root": out / "tb"} if "TensorBoard" in
                                        cfg.logger._target_ else {}))
    w_true = reward_basis.true_weights(tuple(cfg.env.true_reward_weights))
    rng = np.random.default_rng(cfg.seed)
    split = list(cfg.split)
    if sum(split) != cfg.n_demonstrations:
        raise ValueError(f"split {split} sums to {sum(split)}, not n_demonstrations="
                         f"{cfg.n_demonstrations}; make them agree.")
    print(f"{layout.n_experts} experts, {len(split)} learners holding {split} demonstrations;"
          f" {model.n_pairs:,} state-action pairs")

    # Experts: the demonstrations and the two reference rows.
    exp_solver = build(cfg.solver, model=model, dtype=torch.float64) \
        if model.n_pairs < 5_000_000 else solver
    experts = expert_solution(solver=exp_solver, reward_features=reward_basis(),
                              reward_weights=w_true, temperature=cfg.expert_temperature)
    nominal = expert_solution(solver=exp_solver, reward_features=reward_basis(),
                              reward_weights=w_true, constrained=False,
                              temperature=cfg.expert_temperature)
    demos = sample_trajectories(experts, cfg.n_demonstrations, rng)
    save_demonstrations(out / "demos.npz", demos)
    shards = partition_demonstrations(demos, split)
    ctx = {"model": model, "layout": layout, "episodes": cfg.eval_episodes,
           "reward_table": reward_basis().weighted(w_true).local[:, :, 0],
           "rng": torch.Generator().manual_seed(cfg.seed), "w_true": w_true,
           "true": cost_basis.true_constraints().numpy()}

    a = cfg.algo

    def make_trainer(shards_: list[Demonstrations], n_learners: int) -> DICRL:
        graph = {k: build(cfg.graph[k], n_learners=n_learners) for k in ("inner", "outer")}
        # Consensus averages the learners' steps α m^[v] ∇G^[v] into α (m / N_L) ∇G; one
        # learner with all m trajectories takes the same step on G with α / N_L.
        steps = instantiate(a.steps)
        scale = n_learners / len(split)
        steps = type(steps)(alpha_bar=steps.alpha_bar * scale, beta_bar=steps.beta_bar,
                            beta_power=steps.beta_power)
        return DICRL(
            solver=solver, reward_basis=reward_basis, cost_basis=cost_basis, shards=shards_,
            trajectory_counts=[s.n_trajectories for s in shards_],
            communicator=build(cfg.comm, n_learners=n_learners),
            inner_schedule=graph["inner"], outer_schedule=graph["outer"],
            steps=steps, inner_steps=a.inner_steps,
            lsca_curvature=a.lsca_curvature, prune_accrued=a.prune_accrued,
            init_cost_weights=a.init_cost_weights, init_reward_weights=a.init_reward_weights,
            init_multiplier=a.init_multiplier, inner_method=a.inner_method,
            inner_step=a.inner_step * scale, progress=True)

    def log_outer(run_of, trainer: DICRL, info: dict) -> None:
        n = info["outer_iteration"]
        for i in range(len(trainer.local)):
            run = run_of(i)
            learned = learned_constraints(trainer.state.cost_weights[i], a.threshold)
            logger.scalar(run, "outer/multiplier", info["multiplier"][i], n)
            logger.scalar(run, "outer/lga_norm", info["lga_norm"][i], n)
            logger.scalar(run, "eval/FPR", false_positive_rate(learned, ctx["true"]), n)
            logger.scalar(run, "eval/FNR", false_negative_rate(learned, ctx["true"]), n)
            logger.scalar(run, "eval/RFD", reward_function_distance(
                trainer.state.eta_bar[i, :-1], w_true), n)
        logger.scalar("network", "consensus/max_pairwise_cost_distance",
                      trainer.disagreement(), n)

    ckpt_path = out / "checkpoint.pt"
    saved: dict = {}
    if cfg.resume and ckpt_path.exists():
        # weights_only: tensors and plain containers, never arbitrary pickled objects
        saved = torch.load(ckpt_path, weights_only=True)
        done = {k: v["outer_iteration"] for k, v in saved.items()}
        print(f"resuming from {ckpt_path} (outer iterations done: {done})")
    elif cfg.resume:
        print(f"resume=true but no checkpoint in {out}; starting from scratch")

    def checkpoint(name: str, trainer: DICRL) -> None:
        saved[name] = trainer.state_dict()
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save(saved, tmp)
        tmp.replace(ckpt_path)  # atomic: a crash leaves the previous checkpoint intact
        crash = os.environ.get("DICRL_CRASH_AFTER")  # fault injection for tests
        if crash == f"{name}:{trainer.state.outer_iteration}":
            os.kill(os.getpid(), 9)

    methods: dict = {}
    runs = [("D-ICRL", shards, len(shards), lambda i: f"learner{i}")]
    if a.run_c_icrl:
        pooled = Demonstrations(states=demos.states, actions=demos.actions,
                                n_cells=demos.n_cells, n_actions=demos.n_actions)
        runs.append(("C-ICRL", [pooled], 1, lambda i: "c_icrl"))
    trainers = {}
    for name, shards_, n_l, run_of in runs:
        trainer = make_trainer(shards_, n_l)
        if name in saved:
            trainer.load_state_dict(saved[name])

        def after_outer(t, info, r=run_of, name=name):
            log_outer(r, t, info)
            if t.state.outer_iteration % cfg.checkpoint_every == 0:
                checkpoint(name, t)

        trainer.train(a.outer_iterations, callback=after_outer)
        checkpoint(name, trainer)
        trainers[name] = trainer
        rows = [learner_row(trainer, i, ctx, a.threshold, a.prune_min_gain)
                for i in range(n_l)]
        methods[name] = {"D": "✓" if n_l > 1 else "×", "NATR": "✓", "learners": rows}
        for i in range(n_l):
            img = constraint_map(layout, cost_basis, trainer.state.cost_weights[i], a.threshold,
                                 f"{name} learner {i + 1}: learned cell constraints (x)")
            logger.image(run_of(i), "eval/constraint_map", img, a.outer_iterations)
            import matplotlib.image

            matplotlib.image.imsave(out / f"constraints_{name}_{i + 1}.png", img)
            logger.scalar(run_of(i), "eval/CR", rows[i]["CR_mean"], a.outer_iterations)
            logger.scalar(run_of(i), "eval/CVR", rows[i]["CVR"], a.outer_iterations)
    for name, sol in (("Experts (ground truth)", experts), ("Experts (nominal)", nominal)):
        row = evaluate(sol.policy_at, ctx)
        row.update(FPR=None, FNR=None, RFD=0.0, SR=None)
        methods[name] = {"learners": [row]}
    logger.close()

    d = trainers["D-ICRL"]
    results = {
        "experiment": cfg.name, "wall_s": time.perf_counter() - t_start,
        "methods": {k: {"learners": v["learners"]} for k, v in methods.items()},
        "consensus_max_pairwise_cost_distance": d.disagreement(),
        "history": {k: [{**h, "seconds": None} for h in t.history]  # timings vary run to run
                    for k, t in trainers.items()},
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=1))
    tmp.replace(out / "results.json")  # atomic: a crash never leaves half a file
    print()
    print_table(methods)
    print(f"\nwall time {results['wall_s']:.0f} s; consensus max ‖ω_c − ω_c'‖ = "
          f"{results['consensus_max_pairwise_cost_distance']:.1e}")
    print(f"results, TensorBoard runs (tb/) and figures in {out.resolve()}")


if __name__ == "__main__":
    main()
