"""``respecd schema``: the profile's JSON Schema, for yaml-language-server and other editors."""

from __future__ import annotations

import argparse
import json

from respecd.config import json_schema


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="FILE", help="write to FILE instead of stdout")


def main(args: argparse.Namespace) -> int:
    text = json.dumps(json_schema(), indent=2) + "\n"
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            fh.write(text)
    else:
        print(text, end="")
    return 0
