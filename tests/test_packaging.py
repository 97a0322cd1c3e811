"""Every folder the package ships is declared: setuptools warns ("Package would be ignored",
a banner per folder) about a folder inside a package that holds files but is not listed."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_every_shipped_folder_is_a_declared_package() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    declared = set(setup["packages"])
    roots = {"respecd": REPO / "respecd", **{name: REPO / path for name, path in setup["package-dir"].items()}}
    missing = []
    for name, root in roots.items():
        for folder in [root, *root.rglob("*")]:
            if not folder.is_dir() or "__pycache__" in folder.parts or not any(f.is_file() for f in folder.iterdir()):
                continue
            package = ".".join([name, *folder.relative_to(root).parts])
            if package not in declared:
                missing.append(package)
    assert missing == [], f"add to [tool.setuptools] packages (and package-data): {missing}"
    for package, patterns in setup["package-data"].items():
        assert package in declared, package
        folder = roots.get(package) or REPO / Path(*package.split("."))
        assert all(any(folder.glob(p)) for p in patterns), (package, patterns)
