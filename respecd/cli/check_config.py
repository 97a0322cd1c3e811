"""``respecd check-config FILE...``: validate profiles, every problem on its own line."""

from __future__ import annotations

import argparse
import sys

from respecd.config import load_profile
from respecd.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="profile YAML files (or builtin:NAME)")


def main(args: argparse.Namespace) -> int:
    failed = False
    for source in args.files:
        try:
            profile = load_profile(source)
        except ConfigError as err:
            failed = True
            for line in err.problems:
                print(line, file=sys.stderr)
            continue
        print(f"{source}: ok ({profile.name}, {len(profile.sensors)} sensors)")
    return 2 if failed else 0
