"""Train D-ICRL (and C-ICRL, and the baselines) on the configured environment and report
the paper's table.

    python experiments/train.py experiment=quick [seed=1] [graph=ring] [features/cost=per_expert]
    python experiments/train.py experiment=table1      # Table 1: + ME-greedy, MCE-greedy rows
    python experiments/train.py experiment=table2      # Table 2: the drone arena
    python experiments/train.py comm=distributed       # one process per learner (spawned here)
    torchrun --standalone --nproc_per_node N_L experiments/train.py comm=distributed

Writes ``results.json``, TensorBoard runs (``tb/``), figures and the demonstrations into
the Hydra run directory and prints the table. This file only reads the config: the
objects are built by ``common`` and launched by :mod:`dicrl_torch.runs.launch`.

The config is checked before anything is computed (exit code 2); a first SIGINT/SIGTERM
checkpoints and exits with 128 + the signal, printing the command that resumes; a NaN or
inf exits with 1 naming where it arose (docs/design.md).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import hydra
import torch
from common import ConfigExperiment, check_config, check_shard_contents
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from dicrl_torch.runs.launch import launch


def train(cfg: DictConfig, out: Path, overrides: tuple[str, ...] = ()) -> int:
    """Check ``cfg``, run it into ``out``; the exit code (see :mod:`dicrl_torch.runs.launch`;
    2: the config or a shard file was refused, nothing was computed)."""
    t_start = time.perf_counter()
    try:
        check_config(cfg)
        check_shard_contents(cfg)
        experiment = ConfigExperiment(cfg, overrides)
    except ValueError as e:  # a ConfigError, or a shard file that does not fit the run
        print(f"error: {e}", file=sys.stderr, flush=True)
        return 2
    torch.set_num_threads(int(os.environ.get("DICRL_THREADS", torch.get_num_threads())))
    return launch(experiment, out, t_start=t_start)


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    hydra_cfg = HydraConfig.get()
    code = train(cfg, Path(hydra_cfg.runtime.output_dir), tuple(hydra_cfg.overrides.task))
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
