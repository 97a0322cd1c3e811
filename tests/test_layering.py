"""The daemon's modules import none of the offline tooling (respecd.lab) nor its extra.

Every import statement counts, lazy ones inside functions included: a daemon module that
imported the tooling only on one code path would still make it a dependency of the robot.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# the CLI's front-ends to the tooling: `respecd train|eval|calibrate|train-policy|bench`
LAB_COMMANDS = {"train.py", "eval.py", "calibrate.py", "train_policy.py", "bench.py"}
LAB_EXTRA = ("matplotlib", "tqdm")


def daemon_modules() -> list[Path]:
    """Every module under respecd/ and drivers/ but the tooling and its CLI front-ends."""
    modules = sorted((REPO / "respecd").rglob("*.py")) + sorted((REPO / "drivers").rglob("*.py"))
    return [m for m in modules
            if "lab" not in m.relative_to(REPO).parts
            and not (m.parent.name == "cli" and m.name in LAB_COMMANDS)]


def imported_names(path: Path) -> list[tuple[int, str, bool]]:
    """(line, module, guarded) for every import in the file; ``guarded`` when it sits in a
    ``try`` whose handlers catch ImportError (an optional import with a fallback)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: list[tuple[int, str, bool]] = []

    def visit(node: ast.AST, guarded: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name, guarded) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module, guarded))
        if isinstance(node, ast.Try):
            catches = any(_catches_import_error(h) for h in node.handlers)
            for child in node.body:
                visit(child, guarded or catches)
            for child in node.handlers + node.orelse + node.finalbody:
                visit(child, guarded)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, guarded)

    visit(tree, False)
    return found


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    names = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(n, ast.Name) and n.id in ("ImportError", "ModuleNotFoundError") for n in names)


def test_the_layering_test_sees_the_daemon() -> None:
    names = {str(m.relative_to(REPO)) for m in daemon_modules()}
    expected = {"respecd/session.py", "respecd/control/loop.py", "respecd/cli/run.py", "respecd/replay/run.py",
                "drivers/sim.py"}
    assert expected <= names
    assert not any(n.startswith("respecd/lab/") for n in names)


def test_daemon_modules_import_no_lab_tooling() -> None:
    offenders = [f"{m.relative_to(REPO)}:{line}: imports {name}"
                 for m in daemon_modules() for line, name, _ in imported_names(m)
                 if name == "respecd.lab" or name.startswith("respecd.lab.")]
    assert not offenders, "\n".join(offenders)


def test_daemon_modules_need_not_have_the_lab_extra() -> None:
    """matplotlib / tqdm only behind an ImportError fallback (the replay's PNG and progress bar)."""
    offenders = [f"{m.relative_to(REPO)}:{line}: imports {name} without a fallback"
                 for m in daemon_modules() for line, name, guarded in imported_names(m)
                 if name.split(".")[0] in LAB_EXTRA and not guarded]
    assert not offenders, "\n".join(offenders)
