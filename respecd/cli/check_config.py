"""``respecd check-config FILE...``: validate profiles, every problem on its own line."""

from __future__ import annotations

import argparse
import sys

from respecd.config import read_profile
from respecd.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="profile YAML files (or builtin:NAME)")
    parser.add_argument(
        "--state-dir", metavar="DIR", help="where the daemon finds the Q-table (default: as the daemon resolves it)"
    )
    parser.add_argument(
        "--portable", action="store_true",
        help="check the profile away from its robot: leave out this machine's checks (torch device, files that "
             "live on the robot, state directory) and list them; what --replay needs still is checked",
    )


def main(args: argparse.Namespace) -> int:
    """Each profile is validated, then checked against this machine as the daemon would at start
    (files it names, torch device, Q-table): ok here means it starts here. ``--portable`` leaves
    out this machine's checks and says which."""
    from respecd.control.persist import resolve_state_dir
    from respecd.preflight import check_portable, check_profile

    state_dir = resolve_state_dir(args.state_dir) if not args.portable else None
    failed = False
    for source in args.files:
        skipped: list[str] = []
        try:
            loaded = read_profile(source)
            if args.portable:
                problems, skipped = check_portable(loaded)
            else:
                problems = check_profile(loaded, state_dir)
        except ConfigError as err:
            problems = err.problems
        if problems:
            failed = True
            for line in problems:
                print(line, file=sys.stderr)
            continue
        profile = loaded.model
        mode = ", portable" if args.portable else ""
        print(f"{source}: ok ({profile.name}, {len(profile.sensors)} sensors{mode})")
        if skipped:
            print("  left out (this machine's checks, not the profile's):")
        for check in skipped:
            print(f"    {check}")
    return 2 if failed else 0
