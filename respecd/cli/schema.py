"""``respecd schema``: the profile's JSON Schema, for yaml-language-server and other editors.

The shipped profiles start with ``# yaml-language-server: $schema=profile.schema.json``:
the schema sits beside them in the checkout (configs/) and in the installed package
(``respecd/profiles/``). A profile copied elsewhere (``/etc/respecd/``) gets its schema with
``respecd schema --install /etc/respecd/respecd.yaml`` (or the directory), which writes
``profile.schema.json`` beside it so the same header resolves there too.

``respecd schema --validate FILE...`` checks files as written against that schema, as the
editor does: an overlay (``extends:``) passes with only the keys it changes.
"""

from __future__ import annotations

import argparse
import json
import sys
from importlib import resources
from pathlib import Path

from respecd.errors import ConfigError, InputError
from respecd.outputs import check_output_file
from respecd.profile_schema import check_file, json_schema

SCHEMA_NAME = "profile.schema.json"
HEADER = f"# yaml-language-server: $schema={SCHEMA_NAME}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="FILE",
                        help="write to FILE instead of stdout (replaced if it exists; its folder must exist)")
    parser.add_argument("--install", metavar="PROFILE_OR_DIR",
                        help=f"write {SCHEMA_NAME} beside this profile (or into this directory) for its editor header")
    parser.add_argument("--path", action="store_true", help="print where the installed package's schema file is")
    parser.add_argument("--validate", nargs="+", metavar="FILE",
                        help="check profiles (or overlays) as written against the schema; exit 2 on a problem")


def installed_path() -> Path:
    return Path(str(resources.files("respecd.profiles").joinpath(SCHEMA_NAME)))


def main(args: argparse.Namespace) -> int:
    if args.path:
        print(installed_path())
        return 0
    if args.validate:
        return validate(args.validate)
    out = check_output_file("--out", args.out, make_parents=False, example=SCHEMA_NAME)  # open() makes no folder
    text = json.dumps(json_schema(), indent=2) + "\n"
    if args.install:
        return install(Path(args.install), text)
    if out is not None:
        with open(out, "w", encoding="utf-8") as fh:
            fh.write(text)
    else:
        print(text, end="")
    return 0


def install(target: Path, text: str) -> int:
    directory = target if target.is_dir() else target.parent
    if not directory.is_dir():
        raise InputError(f"--install {target}: no such directory {directory}")
    out = directory / SCHEMA_NAME
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as err:
        raise InputError(f"--install: cannot write {out}: {err.strerror or err}") from err
    header = ""
    if target.is_file() and HEADER not in target.read_text(encoding="utf-8", errors="replace").splitlines()[:3]:
        header = f" (add `{HEADER}` as the profile's first line)"
    print(f"{out}: written{header}")
    return 0


def validate(files: list[str]) -> int:
    """Each file against the schema: ``FILE: ok`` or one ``FILE:LINE: path: problem`` line each."""
    failed = False
    for source in files:
        try:
            problems = check_file(source)
        except ConfigError as err:
            problems = err.problems
        for line in problems:
            print(line, file=sys.stderr)
        failed = failed or bool(problems)
        if not problems:
            print(f"{source}: ok (matches the profile schema)")
    return 2 if failed else 0
