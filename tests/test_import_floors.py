"""The library's import floors (docs/design.md §2): a module imports only from its own
floor or the floors below it, so that the layers stay visible and nothing low (an
environment, a solver) depends on something high (a trainer, a run)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dicrl_torch"

# Lowest first; within a floor imports are free. demos (trajectory data) sits below
# solvers: a solver reads demonstrations, the experts' policies live with the solvers.
FLOORS: list[set[str]] = [
    {"io", "logger", "checks"},          # utilities
    {"envs", "features", "demos"},       # environments, feature bases, trajectory data
    {"solvers"},                         # inner solvers and the experts' policies
    {"metrics", "region", "figures", "comm"},  # evaluation, pictures, communication
    {"algos"},                           # D-ICRL, learner models, baselines
    {"runs"},                            # the runner, tasks, checkpoints
    {"bench"},                           # command-line benchmark
]
FLOOR = {part: level for level, parts in enumerate(FLOORS) for part in parts}

MAX_MODULE_LINES = 700
"""A module longer than this holds more than one concern: split it by concern."""
LONG_MODULES: set[str] = set()


def part_of(module: str) -> str | None:
    """``dicrl_torch.algos.dicrl`` -> ``algos``; None outside the package or for the
    package itself."""
    bits = module.split(".")
    return bits[1] if bits[0] == "dicrl_torch" and len(bits) > 1 else None


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in the file, lazy ones inside functions
    included; relative imports resolved against the file's package."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
    return found


def library_files() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_library_module_has_a_floor():
    parts = {part_of(module_name(p)) for p in library_files()} - {None}
    assert parts <= set(FLOOR), f"modules without a floor: {sorted(parts - set(FLOOR))}"


def violations(path: Path) -> list[str]:
    own = part_of(module_name(path))
    if own is None:  # dicrl_torch/__init__.py
        return []
    out = []
    for line, name in imports_of(path):
        target = part_of(name)
        if target is not None and FLOOR[target] > FLOOR[own]:
            out.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({own}, floor "
                       f"{FLOOR[own]}) imports {name} ({target}, floor {FLOOR[target]})")
    return out


@pytest.mark.parametrize("path", library_files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_import_climbs_a_floor(path):
    assert violations(path) == []


def test_every_library_module_is_short():
    long = {str(p.relative_to(PACKAGE)): n for p in library_files()
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    over = {name: n for name, n in long.items() if name not in LONG_MODULES}
    assert not over, (f"modules over {MAX_MODULE_LINES} lines (split them by concern): "
                      f"{over}")
    # A long module that was split must lose its exemption, or it could grow back.
    stale = LONG_MODULES - set(long)
    assert not stale, f"exempt but no longer over {MAX_MODULE_LINES} lines, drop: {stale}"


def test_the_checker_sees_a_climbing_import(tmp_path, monkeypatch):
    # The walker must catch lazy imports inside functions and relative imports.
    fake = tmp_path / "dicrl_torch"
    (fake / "solvers").mkdir(parents=True)
    src = fake / "solvers" / "bad.py"
    src.write_text("def f():\n    from ..algos import dicrl\n    import dicrl_torch.runs\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", fake)
    found = violations(src)
    assert len(found) == 2 and "dicrl_torch.algos" in found[0] and "runs" in found[1]
