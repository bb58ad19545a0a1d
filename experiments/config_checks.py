"""The config checks that span several groups: an option of another environment (a basis,
solver or baseline of the grid world on a continuous game, or the reverse: the classes say
which kind they serve, ``env_kind``), keys nothing reads, and what ties groups together.
The value rules live in the library's constructors, which ``common.check_config`` builds
before anything is computed, adding these problems."""

from __future__ import annotations

import difflib
import inspect
import os
from pathlib import Path
from typing import Any

from hydra.utils import get_class, get_object
from omegaconf import DictConfig, OmegaConf

from dicrl_torch.comm.distributed import DistributedCommunicator
from dicrl_torch.runs.settings import GREEDY_BASELINE, GRID_BASELINES


class ConfigError(ValueError):
    """The configuration has an unknown key, a value out of range or groups that clash."""


_HYDRA_KEYS = {"_target_", "_partial_", "_args_", "_recursive_", "_convert_"}


def unknown_keys(node, known: set[str], path: str = "", skip: frozenset[str] = frozenset()
                 ) -> list[str]:
    """Keys of ``node`` (and below) that nothing reads (a misspelt ``+key=...`` gets past
    Hydra's struct mode): a node with a ``_target_`` is checked against its signature, one
    above a ``known`` dotted key against those; others (the game's ``env``) and the nodes
    at ``skip`` are not."""
    if not isinstance(node, DictConfig) or path in skip:
        return []
    prefix, reader = (f"{path}.", f"'{path}'") if path else ("", "the top level")
    names = {k[len(prefix):].split(".")[0] for k in known if k.startswith(prefix)}
    if "_target_" in node:
        try:
            params = inspect.signature(get_object(node["_target_"])).parameters
        except Exception as e:  # noqa: BLE001 - any import failure is a config error
            return [f"{path}._target_={node['_target_']!r} cannot be imported ({e}); fix the "
                    f"class path."]
        names, reader = (set() if any(p.kind is p.VAR_KEYWORD for p in params.values())
                         else set(params) | _HYDRA_KEYS), node["_target_"]
    problems = []
    for key in sorted(set(node.keys()) - names) if names else ():
        close = difflib.get_close_matches(key, sorted(names - _HYDRA_KEYS), n=1)
        hint = f"did you mean '{close[0]}'? Remove" if close else "remove"
        problems.append(f"unknown key '{prefix}{key}': {reader} takes no option '{key}'; "
                        f"{hint} it or fix its spelling.")
    for key in node.keys():
        problems += unknown_keys(node[key], known, f"{prefix}{key}", skip)
    return problems


def cross_group_problems(cfg, misfits: dict[str, str]) -> list[str]:
    """What ties groups together: ``split`` and ``n_demonstrations``, shard files and the
    environment, the continuous games' rule and baseline, the methods run and how torchrun
    started the processes (the shard files' own checks: ``common.shard_file_problems``)."""
    problems, continuous = [], env_fit(cfg.env)[0] == "continuous"
    split, n, simulated = cfg.get("split"), cfg.get("n_demonstrations"), is_simulated(cfg)
    if OmegaConf.is_list(split) and all(isinstance(m, int) for m in split) and sum(split) != n:
        problems.append(f"split={list(split)} sums to {sum(split)}, not n_demonstrations="
                        f"{n!r}; make them agree (e.g. n_demonstrations={sum(split)}).")
    if cfg.get("shard_files") is not None and continuous:
        problems.append("shard_files is for the grid world; the continuous games record "
                        "their own demonstrations. Set shard_files=null.")
    if continuous and OmegaConf.select(cfg, "algo.constraint_rule") == "certificate":
        problems.append("algo.constraint_rule=certificate needs the grid world's exact "
                        "solver (one solve per unseen feature); the continuous games keep "
                        "the paper's rule: set algo.constraint_rule=threshold.")
    if OmegaConf.select(cfg, "algo.run_d_icrl", default=True) is False:
        if continuous and "baselines" not in misfits and cfg.baselines.get("run"):
            problems.append("algo.run_d_icrl=false leaves the continuous games' greedy "
                            "baseline without its reward (D-ICRL's learned one, as in the "
                            "paper); set algo.run_d_icrl=true or baselines=none.")
        elif not simulated:
            problems.append("algo.run_d_icrl=false trains no learner processes, so "
                            "comm=distributed has nothing to run; use comm=simulated.")
    # torchrun starts one process per learner, each running only its own.
    world = int(os.environ["WORLD_SIZE"]) if os.environ.get("WORLD_SIZE", "").isdigit() else 0
    if world > 1 and simulated:
        problems.append(f"Started as one of WORLD_SIZE={world} processes (torchrun?) with "
                        f"comm={cfg.comm._target_}, which runs every learner in each "
                        f"process; add comm=distributed.")
    elif (world and not simulated and "RANK" in os.environ and OmegaConf.is_list(split)
          and world != len(split)):
        problems.append(f"torchrun started WORLD_SIZE={world} processes but split="
                        f"{list(split)} has {len(split)} learners (one process per learner);"
                        f" run torchrun with --nproc_per_node {len(split)} (times the nodes),"
                        f" or change split.")
    return problems


def is_simulated(cfg) -> bool:
    """All learners in one process (a bad ``comm._target_`` too: the key checks say)."""
    try:
        return not issubclass(get_class(cfg.comm._target_), DistributedCommunicator)
    except Exception:  # noqa: BLE001 - reported by the key checks
        return True


# ---------------------------------------------------------------- options of the environment
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
# The config groups whose options serve one kind of environment, what an option is, and how
# the messages name the kinds (the classes' ``env_kind``) and the games (their ``game``).
KIND_GROUPS = {"features/reward": "a basis", "features/cost": "a basis",
               "solver": "a solver", "baselines": "baselines"}
KIND_WORDS = {"grid": "the grid world",
              "continuous": "the continuous games (the drone arena, the MPE spread)"}
GAME_WORDS = {"drones": "the drone arena", "mpe_spread": "the MPE spread"}
BASELINE_ROWS = {"grid": tuple(GRID_BASELINES), "continuous": (GREEDY_BASELINE,)}


def env_fit(env) -> tuple[str, str | None]:
    """(kind, game) of an environment node: a continuous game has ``arena`` settings."""
    if OmegaConf.select(env, "arena", default=None) is None:
        return "grid", None
    spread = OmegaConf.select(env, "layout._target_", default="").endswith("mpe.SpreadLayout")
    return "continuous", "mpe_spread" if spread else "drones"


def _identity(group: str, node) -> Any:
    """What tells options apart: baseline rows, or a class path (the drones' solver node:
    its ``solver._target_``)."""
    if group == "baselines":
        run = node.get("run") if OmegaConf.is_dict(node) else None
        return tuple(run) if OmegaConf.is_list(run) else None
    targets = _targets(node)
    return targets.get("", targets.get(".solver"))


def option_fit(group: str, node) -> tuple[str | None, str | None]:
    """The kind of environment and the game the option ``node`` of ``group`` serves (None:
    any): its class's ``env_kind`` and ``game``, or for baselines its rows'."""
    ident = _identity(group, node)
    if group == "baselines":
        return next((k for k, rows in BASELINE_ROWS.items()
                     if ident and all(x in rows for x in ident)), None), None
    try:
        cls = get_class(ident) if ident else None
    except Exception:  # noqa: BLE001 - an import failure is reported by the key checks
        return None, None
    return getattr(cls, "env_kind", None), getattr(cls, "game", None)


def _options(group: str) -> dict[str, DictConfig]:
    return {p.stem: OmegaConf.load(p) for p in sorted((CONFIGS / group).glob("*.yaml"))}


def _chosen_options() -> set[tuple[str, str]]:
    """(group, option) pairs train.yaml or an experiment chooses: fixes name them first."""
    entries = [e for p in [CONFIGS / "train.yaml", *(CONFIGS / "experiment").glob("*.yaml")]
               for e in OmegaConf.load(p).get("defaults", []) if OmegaConf.is_dict(e)]
    return {(str(k).removeprefix("override").strip().lstrip("/"), str(o))
            for e in entries for k, o in e.items()}


def _targets(node, path: str = "") -> dict[str, str]:
    """The class paths under ``node``, by path (``""``: its own)."""
    if not OmegaConf.is_dict(node):
        return {}
    found = {path: node["_target_"]} if isinstance(node.get("_target_"), str) else {}
    for key in node:
        found.update(_targets(node[key], f"{path}.{key}") if key != "_target_" else {})
    return found


def _same_values(option: DictConfig, node) -> bool:
    """Whether ``node`` holds every plain (not interpolated) top-level value of the option
    file ``option``."""
    for key in option:
        if OmegaConf.is_interpolation(option, key) or OmegaConf.is_config(option[key]):
            continue
        if not OmegaConf.is_dict(node) or key not in node or node[key] != option[key]:
            return False
    return True


def misfit_options(cfg) -> dict[str, str]:
    """The options of ``KIND_GROUPS`` that serve another kind of environment or another game:
    the config path of the option's node -> what it is, whose, and the group's that fit."""
    (kind, game), problems, chosen = env_fit(cfg.env), {}, None
    for group, noun in KIND_GROUPS.items():
        path = group.replace("/", ".")
        node = OmegaConf.select(cfg, path, default=None)
        theirs, their_game = option_fit(group, node)
        if theirs is None or (theirs == kind and their_game in (None, game)):
            continue
        options, chosen = _options(group), chosen or _chosen_options()
        same = [o for o, n in options.items() if _identity(group, n) == _identity(group, node)]
        # Options of one class (local_relu, local_relu_drones): the one whose values match.
        name = next((f"{group}={o}" for o in sorted(
            same, key=lambda o: not _same_values(options[o], node))), None)
        if name is None and group == "baselines":  # rows of its own: the rows' check says
            continue
        name = name or f"{path}._target_={_identity(group, node)}"
        fits = {o: option_fit(group, n) for o, n in options.items()}
        fit = sorted((o for o, (k, g) in fits.items() if k == kind and g in (None, game)),
                     key=lambda o: ((group, o) not in chosen, o))
        fit += [o for o, (k, _) in fits.items() if k is None]
        fix = (f"use {group}={fit[0]}" + (f" (or {', '.join(fit[1:])})" if fit[1:] else "")
               if fit else f"no {group} option serves it; add one")
        whose = (KIND_WORDS.get(theirs, theirs) if theirs != kind or their_game is None
                 else f"{GAME_WORDS.get(their_game, their_game)} only")
        envs = {o: n for o, n in _options("env").items() if env_fit(n)[0] == kind}
        same = [o for o, n in envs.items() if _targets(n) == _targets(cfg.env)]
        env_name = f"env={same[0]}" if len(same) == 1 else "env=" + " or env=".join(envs)
        problems[path] = (f"{name} {'are' if group == 'baselines' else 'is'} {noun} of "
                          f"{whose}; with {env_name} {fix}.")
    return problems
