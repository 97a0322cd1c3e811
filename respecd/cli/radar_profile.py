"""``respecd radar-profile``: print the chirp cfg and the four radar figures for a table key.

The output is a valid TI cfg file (figures as ``%`` comments), so it can be saved and sent
with any tool. Exit status 1 when the profile breaks a TI limit (stated on stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from respecd.argtypes import positive_float
from respecd.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--prefer", choices=("range", "velocity"), default="range", help="radar preference (action)")
    parser.add_argument("--fps", type=positive_float, default=10.0, help="frame rate 1-30 Hz (nearest table row)")
    parser.add_argument("--board", choices=("isk", "aop"), default="isk", help="antenna board (chirp order, gains)")
    parser.add_argument("--tx", type=int, choices=(2, 3), default=3, help="TX antennas in TDM (2: azimuth only, isk)")
    parser.add_argument("--firmware", choices=("xwr68xx_mmw_demo", "xwr64xx_mmw_demo", "xwr64xxAOP_mmw_demo"),
                        help="demo image on the board (default: xwr68xx_mmw_demo on isk, xwr64xxAOP_mmw_demo on aop)")
    parser.add_argument("--max-points", type=int, default=100, help="points per frame budgeted in the frame timeline")
    parser.add_argument("--range-profile", action="store_true", help="also stream the range profile (TLV 2)")
    parser.add_argument("--base", metavar="CFG", help="keep this cfg's non-chirp lines (CFAR, calibration, ...)")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON object, no cfg")
    parser.add_argument("--table", action="store_true", help="print the whole lookup table (one row per key)")


def main(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except BrokenPipeError:  # `respecd radar-profile | head`: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _run(args: argparse.Namespace) -> int:
    from respecd.radar import cfg
    from respecd.radar.chirp import RATES_HZ, lookup

    if not 1.0 <= args.fps <= 30.0:
        raise InputError(f"--fps {args.fps:g}: expected a frame rate from 1 to 30 Hz")
    if args.max_points < 0:
        raise InputError(f"--max-points {args.max_points}: expected 0 or more")
    if args.table:
        return _print_table(args, RATES_HZ)
    profile = lookup(args.prefer, args.fps, args.tx, args.max_points, args.range_profile)
    base = cfg.read_cfg(args.base) if args.base else None
    lines = cfg.render(profile, args.board, base, args.firmware)  # ConfigError for an unsupported TX/board
    problems = profile.problems()
    if args.json:
        firmware = args.firmware or cfg.DEFAULT_FIRMWARE[args.board]
        figures = {"prefer": args.prefer, "fps": profile.rate_hz, "loops": profile.loops, **profile.figures()}
        figures |= {"uart_bytes_per_frame": profile.uart_bytes_per_frame(), "max_points": profile.max_points,
                    "firmware": firmware, "problems": problems}
        print(json.dumps(figures))
    else:
        if profile.rate_hz != args.fps:
            print(f"% requested {args.fps:g} fps; nearest table row is {profile.rate_hz:g} fps")
        print("\n".join(cfg.header(profile, args.board, args.firmware)))
        print("\n".join(lines))
    for problem in problems:
        print(f"respecd: radar-profile: {problem}", file=sys.stderr)
    return 1 if problems else 0


def _print_table(args: argparse.Namespace, rates: tuple[int, ...]) -> int:
    from respecd.radar.chirp import lookup

    print("prefer    fps loops idle_us range_res_m max_range_m vmax_mps vres_mps active_ms uart_ms problems")
    bad = 0
    for prefer in ("range", "velocity"):
        for rate in rates:
            p = lookup(prefer, rate, args.tx, args.max_points, args.range_profile)
            f, problems = p.figures(), p.problems()
            bad += bool(problems)
            print(
                f"{prefer:<9} {rate:>3} {p.loops:>5} {p.idle_us:>7g} {f['range_resolution_m']:>11} "
                f"{f['max_range_m']:>11} {f['max_velocity_mps']:>8} {f['velocity_resolution_mps']:>8} "
                f"{f['active_frame_ms']:>9} {p.uart_ms:>7.2f} {'; '.join(problems) or '-'}"
            )
    return 1 if bad else 0
