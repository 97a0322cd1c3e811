"""Layers point one way: cli -> lab -> the daemon's packages.

The daemon (respecd/ outside cli/ and lab/, and drivers/) imports neither the command line nor
the offline tooling (respecd.lab); the lab imports no command line: its tools are called by
``respecd`` subcommands, which parse their arguments with the core's ``respecd.argtypes``. Of
the command line, only the lab's front-ends (``respecd adapt|train|eval|calibrate|train-policy|bench|
experiment|fleet``) import the lab. Every import statement counts, lazy ones inside functions
included: a daemon module that imported the tooling on one code path would still make it a
dependency of the robot.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# the CLI's front-ends to the tooling
LAB_COMMANDS = {"adapt.py", "train.py", "eval.py", "calibrate.py", "train_policy.py", "bench.py", "experiment.py",
                "fleet.py"}
LAB_EXTRA = ("matplotlib", "tqdm")


def layer(path: Path) -> str:
    """'cli', 'lab-command' (a cli front-end to the lab), 'lab' or 'daemon' for a module path under REPO."""
    parts = path.relative_to(REPO).parts
    if parts[:2] == ("respecd", "lab"):
        return "lab"
    if parts[:2] == ("respecd", "cli"):
        return "lab-command" if parts[-1] in LAB_COMMANDS else "cli"
    if parts == ("respecd", "__main__.py"):
        return "cli"
    return "daemon"


# what each layer must not import (module prefixes)
FORBIDDEN = {"daemon": ("respecd.cli", "respecd.lab"), "cli": ("respecd.lab",), "lab": ("respecd.cli",),
             "lab-command": ()}


def modules() -> list[Path]:
    return sorted((REPO / "respecd").rglob("*.py")) + sorted((REPO / "drivers").rglob("*.py"))


def imported_names(source: str, filename: str = "<test>") -> list[tuple[int, str, bool]]:
    """(line, module, guarded) for every import in ``source``: ``from respecd import cli`` counts
    as ``respecd.cli``; ``guarded`` when it sits in a ``try`` whose handlers catch ImportError
    (an optional import with a fallback)."""
    found: list[tuple[int, str, bool]] = []

    def visit(node: ast.AST, guarded: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name, guarded) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module, guarded))
            found.extend((node.lineno, f"{node.module}.{alias.name}", guarded) for alias in node.names)
        if isinstance(node, ast.Try):
            catches = any(_catches_import_error(h) for h in node.handlers)
            for child in node.body:
                visit(child, guarded or catches)
            for child in node.handlers + node.orelse + node.finalbody:
                visit(child, guarded)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, guarded)

    visit(ast.parse(source, filename=filename), False)
    return found


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    names = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(n, ast.Name) and n.id in ("ImportError", "ModuleNotFoundError") for n in names)


def violations(path: Path, source: str | None = None) -> list[str]:
    """Each import of ``path`` (its text, or ``source``) that points against the layers."""
    text = path.read_text() if source is None else source
    own = layer(path)
    found = {line: name for line, name, _ in reversed(imported_names(text, str(path)))
             if any(name == p or name.startswith(p + ".") for p in FORBIDDEN[own])}  # one per statement
    return [f"{path.relative_to(REPO)}:{line}: the {own} layer imports {name}" for line, name in sorted(found.items())]


def test_the_layers_are_seen() -> None:
    layers: dict[str, set[str]] = {}
    for m in modules():
        layers.setdefault(layer(m), set()).add(str(m.relative_to(REPO)))
    assert {"respecd/session.py", "respecd/daemon.py", "respecd/argtypes.py", "drivers/sim.py"} <= layers["daemon"]
    assert {"respecd/cli/run.py", "respecd/cli/check_config.py", "respecd/__main__.py"} <= layers["cli"]
    assert {"respecd/cli/bench.py", "respecd/cli/experiment.py"} <= layers["lab-command"]
    assert "respecd/lab/bench/pipeline.py" in layers["lab"]


def test_imports_point_one_way() -> None:
    offenders = [v for m in modules() for v in violations(m)]
    assert not offenders, "\n".join(offenders)


@pytest.mark.parametrize(("where", "statement"), [
    ("respecd/perception/calibration.py", "from respecd.argtypes import resolution\nfrom respecd.cli.args import seed"),
    ("respecd/session.py", "def f():\n    from respecd.lab.bench import pipeline"),
    ("drivers/sim.py", "import respecd.lab.experiment.rollout"),
    ("respecd/record/__init__.py", "from respecd import cli"),
    ("respecd/lab/experiment/trace.py", "def main():\n    from respecd.cli import train_policy"),
    ("respecd/lab/bench/live.py", "from respecd.cli.run import make_recorder"),
    ("respecd/cli/run.py", "from respecd.lab.bench import BENCHES"),
])
def test_an_import_against_the_layers_is_caught(where: str, statement: str) -> None:
    assert violations(REPO / where, statement), f"{where}: {statement!r} was not caught"
    assert not violations(REPO / where, "from respecd.argtypes import seed\nimport respecd.session")


def test_daemon_modules_need_not_have_the_lab_extra() -> None:
    """matplotlib / tqdm only behind an ImportError fallback (the replay's PNG and progress bar)."""
    offenders = [f"{m.relative_to(REPO)}:{line}: imports {name} without a fallback"
                 for m in modules() if layer(m) in ("daemon", "cli")
                 for line, name, guarded in imported_names(m.read_text(), str(m))
                 if name.split(".")[0] in LAB_EXTRA and not guarded]
    assert not offenders, "\n".join(offenders)


RUNTIME_EXTRAS = ("onnxruntime", "openvino", "onnx")  # perception.runtime's extras: respecd[onnx], respecd[openvino]


def test_only_the_runtime_back_ends_import_the_runtime_extras() -> None:
    """The daemon on runtime torch never needs ONNX Runtime or OpenVINO: their imports live in the back-end
    modules the registry imports when a profile names them (or behind an ImportError fallback)."""
    back_ends = REPO / "respecd" / "perception" / "runtimes"
    offenders = [f"{m.relative_to(REPO)}:{line}: imports {name}"
                 for m in modules() if layer(m) in ("daemon", "cli") and m.parent != back_ends
                 for line, name, guarded in imported_names(m.read_text(), str(m))
                 if name.split(".")[0] in RUNTIME_EXTRAS and not guarded]
    assert not offenders, "\n".join(offenders)


@pytest.mark.slow
def test_the_runtime_torch_daemon_imports_no_runtime_extra() -> None:
    """Loading the shipped detector on runtime torch imports none of the extras (a fresh interpreter)."""
    import subprocess
    import sys

    code = ("import sys; from respecd.perception.config import PerceptionConfig; "
            "from respecd.perception.detector import FusionDetector; FusionDetector.load(PerceptionConfig()); "
            f"print(sorted(m for m in {RUNTIME_EXTRAS!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip().splitlines()[-1] == "[]"
