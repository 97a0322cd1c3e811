"""The simulator's scenarios under static, heuristic and RL: accuracy, compute, energy, bandwidth.

``respecd bench scenarios [--json OUT] [--quick] [--worlds N] [--log LOG]``. Runs on the
simulated rover (held-out world seeds, never used by ``train-policy``; ``--worlds N``: N sets
of worlds, pooled, with the spread over sets) or, with ``--log``, counterfactually on a
recorded session. Also writes a Markdown table (``--markdown``) and a figure (``--figure``).
See docs/RESULTS.md for what the figures mean.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from respecd.argtypes import positive_float, positive_int, seed
from respecd.lab.experiment.platforms import DEFAULT_PLATFORM, LATENCY_HELP
from respecd.outputs import check_output_dir, check_output_file

if TYPE_CHECKING:
    from respecd.config import Profile

QUICK_DURATION_S = 4.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="builtin:sim-rover", help="profile (sensors, controller, simulation)")
    parser.add_argument("--weights", help="detector checkpoint (default: the profile's perception.weights)")
    parser.add_argument("--table", type=Path, help="Q-table for the rl policy (default: the shipped table)")
    parser.add_argument("--quick", action="store_true", help=f"CI size: {QUICK_DURATION_S:g} s per scenario")
    parser.add_argument("--duration", type=positive_float, help="seconds per scenario (default: the profile's, 30)")
    parser.add_argument("--samples-per-s", type=positive_float, default=1.0,
                        help="detector outcomes scored per second (> 0, default 1)")
    parser.add_argument("--seed", type=seed,
                        help="first world seed, >= 0 (default 1000: held out from training)")
    parser.add_argument("--worlds", type=int, default=1, metavar="N",
                        help="sets of worlds (one world per scenario each, seeds SEED .. SEED + N x scenarios - 1): "
                             "figures pooled over the sets, with their spread (default 1)")
    parser.add_argument("--log", type=Path, help="run on a recorded MCAP session instead of the simulator")
    parser.add_argument("--markdown", type=Path, help="write the Markdown table here")
    parser.add_argument("--figure", type=Path, help="write the PNG figure here")
    parser.add_argument("--no-cache", action="store_true", help="keep detector outcomes in memory only")
    parser.add_argument("--cache-dir", type=Path, help="outcome cache folder (default $XDG_CACHE_HOME/respecd)")
    parser.add_argument("--random-detector", action="store_true",
                        help="randomly initialised detector instead of the checkpoint (smoke tests only)")
    parser.add_argument("--latency-repeats", type=positive_int,
                        help="timed calls per resolution, at least 1 (default 5, quick 2)")
    parser.add_argument("--latency-clock", choices=("wall", "cpu"), default="wall",
                        help="--latency measured: time the detector calls in wall time (default) or in the "
                             "process's CPU time (a shared, busy machine: what one quiet core would take)")
    parser.add_argument("--latency", default=DEFAULT_PLATFORM, metavar="orin-nano|cpu|FILE|measured",
                        help=f"{LATENCY_HELP} (default {DEFAULT_PLATFORM})")
    parser.add_argument("--old-heuristic", action="store_true",
                        help="run the documented heuristic rules alone too, beside the tuned ones (old-heuristic)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: when stderr is a terminal)")


def _table_path(args: argparse.Namespace) -> Path:
    from respecd.errors import InputError
    from respecd.lab.experiment.setup import shipped_table_path

    path = args.table or shipped_table_path()
    if not path.is_file():
        raise InputError(f"{path}: no Q-table (train one with `respecd train-policy`, or pass --table)")
    return path


def _table_label(args: argparse.Namespace, path: Path) -> str:
    """The table as the JSON names it: the path as given, or the shipped one by name, never the
    checkout's absolute path (two clones compare equal); its SHA-256 says which table it was."""
    import hashlib

    name = str(args.table) if args.table is not None else f"shipped {path.name}"
    return f"{name} sha256:{hashlib.sha256(path.read_bytes()).hexdigest()[:16]}"


def run(args: argparse.Namespace) -> dict[str, Any]:
    from respecd.config import load_profile
    from respecd.lab.experiment import latency as lat
    from respecd.lab.experiment import platforms
    from respecd.lab.experiment.compare import run_sets
    from respecd.lab.experiment.heuristic import TUNED, description
    from respecd.lab.experiment.rollout import Rollout, controller_for
    from respecd.lab.experiment.setup import load_detector, rgb_resolutions

    start, load_before = time.monotonic(), os.getloadavg()
    check_output_file("--markdown", args.markdown, example="scenarios.md")  # written after every run: checked now
    check_output_file("--figure", args.figure, example="scenarios.png")
    if not args.no_cache:
        check_output_dir("--cache-dir", args.cache_dir)
    _check(args)
    profile = load_profile(args.profile)
    table = _table_path(args)
    resolutions = rgb_resolutions(controller_for(profile, "static"))
    pinned = platforms.pinned(args.latency, resolutions)  # a bad file fails first
    detector = load_detector(profile, args.weights, args.random_detector)
    if args.log is not None:
        from respecd.lab.experiment.logbench import prepare_log

        evaluator, pieces, frames_for, extra = prepare_log(args, detector)
        sets, people = [pieces], None
    else:
        evaluator, sets, frames_for, extra = _prepare_sim(args, profile, detector)
        people = _people(evaluator, profile)
    repeats = args.latency_repeats or (2 if args.quick else 5)
    latency = pinned or platforms.measured(
        lat.measure(detector, frames_for, resolutions, repeats, lat.CLOCKS[args.latency_clock]), args.latency_clock)
    rollout = Rollout(profile, evaluator, latency.latency, args.samples_per_s, latency.accelerator_w)
    windows = sum(max(1, int(round(p.duration_s / rollout.period))) for pieces in sets for p in pieces)
    bar = _bar(args, (4 if args.old_heuristic else 3) * windows)
    try:
        result = run_sets(profile, rollout, sets, table, (lambda p, r: bar.update()) if bar else None, people,
                          TUNED, args.old_heuristic)
    finally:
        if bar:
            bar.close()
        evaluator.cache.close()
    result.update(extra)
    if args.log is None:
        from respecd.lab.experiment.report import goals

        result["goals"] = goals(result)
    result.update(latency_table=latency.label(), latency_ms=lat.to_json(rollout.latency),
                  accelerator_w=rollout.accelerator_w, heuristic=description(TUNED), table=_table_label(args, table),
                  detector_fingerprint=evaluator.fingerprint,
                  run=_run_facts(args, start, load_before, evaluator))
    _write_outputs(args, result)
    return result


def _run_facts(args: argparse.Namespace, start: float, load_before: tuple[float, ...], evaluator: Any) -> dict:
    """What differs between two runs of the same command: time, load, host, cache (the ``run`` key)."""
    import platform

    import torch

    return {"wall_s": round(time.monotonic() - start, 1), "load_average_start": [round(x, 2) for x in load_before],
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
            "cache": {"hits": evaluator.cache.hits, "misses": evaluator.cache.misses},
            "host": {"machine": platform.machine(), "processor": _cpu_name(), "cpus": os.cpu_count(),
                     "python": platform.python_version(), "torch": torch.__version__},
            "latency_clock": args.latency_clock if args.latency == "measured" else None}


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor()


def _check(args: argparse.Namespace) -> None:
    from respecd.errors import InputError

    if args.worlds < 1:
        raise InputError(f"--worlds: expected at least 1, got {args.worlds}")
    if args.worlds > 1 and args.log is not None:
        raise InputError("--worlds: a recorded log has one set of scenes (drop --worlds or --log)")


def _prepare_sim(args: argparse.Namespace, profile: Profile, detector: Any) -> tuple:
    """The simulator as the source: held-out world seeds, one piece per scenario and world set."""
    from respecd.lab.experiment import latency as lat
    from respecd.lab.experiment.compare import world_seed_range, world_sets
    from respecd.lab.experiment.setup import make_evaluator
    from respecd.lab.experiment.training import EVAL_SEED

    evaluator = make_evaluator(detector, profile, not args.no_cache, args.cache_dir)
    duration = args.duration or (QUICK_DURATION_S if args.quick else profile.simulation.scenario_duration_s)
    seed = EVAL_SEED if args.seed is None else args.seed
    sets = world_sets(profile.simulation.scenarios, seed, args.worlds, duration)
    frames_for = lat.sim_frames(evaluator.world(sets[0][0], profile.simulation), evaluator.inputs)
    extra = {"duration_s_per_scenario": duration, "world_seed": seed, "worlds": args.worlds,
             "world_seeds": world_seed_range(seed, args.worlds, profile.simulation.scenarios)}
    return evaluator, sets, frames_for, extra


def _people(evaluator: Any, profile: Profile) -> Any:
    """How many persons a piece's world places (the statistics count them)."""
    return lambda piece: len(evaluator.world(piece, profile.simulation).state_at(0.0).targets)


def _bar(args: argparse.Namespace, total: int) -> Any:
    import sys

    if not (sys.stderr.isatty() if args.progress is None else args.progress):
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc="bench scenarios", unit="window")


def summary(result: dict[str, Any]) -> str:
    """What a person reads after a run: the pooled figures per policy, their spread over the
    world sets, and the headline."""
    from respecd.lab.experiment.report import headline, number

    spread = result.get("spread", {})
    sets = result.get("worlds", 1)
    lines = [f"latency table: {result.get('latency_table')}; heuristic: {result.get('heuristic', {}).get('name')}",
             f"{'policy':<14} {'mAP@0.5':>8} {'load':>6} {'compute ms/s':>13} {'energy J':>9} {'MB/s':>8} "
             f"{'read MB/s':>10}" + (f"   (pooled over {sets} world sets; [min, max] over sets)" if sets > 1 else "")]
    for policy, v in result.get("pooled", {}).items():
        m = "n/a" if v.get("map50") is None else f"{v['map50']:.3f}"
        line = (f"{policy:<14} {m:>8} {v['accelerator_load']:>6.3f} {v['compute_ms_per_s']:>13.0f} "
                f"{v['energy_j']:>9.1f} {v['bandwidth_bps'] / 1e6:>8.2f} {v['bandwidth_read_bps'] / 1e6:>10.2f}")
        if sets > 1 and policy in spread:
            s = spread[policy]
            line += (f"   mAP [{number(s['map50'][0], '.3f')}, {number(s['map50'][1], '.3f')}]"
                     f" load [{s['accelerator_load'][0]:.3f}, {s['accelerator_load'][1]:.3f}]"
                     f" read MB/s [{s['bandwidth_read_bps'][0] / 1e6:.2f}, {s['bandwidth_read_bps'][1] / 1e6:.2f}]")
        lines.append(line)
    lines += headline(result)
    missed = [g["goal"] for g in result.get("goals", []) if g["met"] is False]
    if result.get("goals"):
        lines.append(f"goals met: {len(result['goals']) - len(missed)} of {len(result['goals'])}"
                     + "".join(f"\n  not met: {g}" for g in missed))
    lines.append(f"{len(result.get('scenarios', []))} scenario rows in {result.get('run', {}).get('wall_s', 0):.0f} s; "
                 "all figures: --json OUT (and --markdown, --figure)")
    return "\n".join(lines)


def _write_outputs(args: argparse.Namespace, result: dict[str, Any]) -> None:
    from respecd.lab.experiment.report import figure, markdown

    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(markdown(result), encoding="utf-8")
    if args.figure:
        figure(result, args.figure)
