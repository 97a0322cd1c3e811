"""``respecd train-policy``: learn the Q-table on the simulated scenarios, fast, on cached
detector outcomes; save it where ``--policy exploit`` finds it and plot the learning curve."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from respecd.argtypes import positive_float, positive_int, seed
from respecd.errors import InputError
from respecd.lab.experiment.platforms import DEFAULT_PLATFORM, LATENCY_HELP
from respecd.outputs import check_output_dir, check_output_file

if TYPE_CHECKING:
    from respecd.config import Profile


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="builtin:sim-rover", help="profile (sensors, controller, simulation)")
    parser.add_argument("--weights", help="detector checkpoint (default: the profile's perception.weights)")
    parser.add_argument("--episodes", type=int, default=40,
                        help="episodes of the seven scenarios (the paper's six, then behind-curtain; default 40)")
    parser.add_argument("--seeds", type=int, default=4, help="training world seeds 0..N-1 (default 4)")
    parser.add_argument("--min-s", type=positive_float, default=10.0, help="shortest scenario run in an episode (s)")
    parser.add_argument("--max-s", type=positive_float, default=30.0, help="longest scenario run in an episode (s)")
    parser.add_argument("--seed", type=seed, default=0,
                        help="seed >= 0 of the episode order, durations and world seeds")
    parser.add_argument("--samples-per-s", type=positive_float, default=1.0,
                        help="detector outcomes per scenario second (> 0)")
    parser.add_argument("--state-dir", help="state directory (default: $STATE_DIRECTORY, else $XDG_STATE_HOME/respecd, "
                        "else ~/.local/state/respecd)")
    parser.add_argument("--out", type=Path, help="table file (default: the profile's table in the state directory)")
    parser.add_argument("--curve", type=Path, help="learning-curve PNG (default: beside the table)")
    parser.add_argument("--resume", action="store_true", help="continue from the table at --out if it matches")
    parser.add_argument("--max-minutes", type=positive_float,
                        help="stop after this many minutes, > 0 (the table is saved)")
    parser.add_argument("--no-cache", action="store_true", help="keep detector outcomes in memory only")
    parser.add_argument("--cache-dir", type=Path, help="outcome cache folder (default $XDG_CACHE_HOME/respecd)")
    parser.add_argument("--random-detector", action="store_true",
                        help="randomly initialised detector instead of the checkpoint (smoke tests only)")
    parser.add_argument("--latency-repeats", type=positive_int, default=3,
                        help="--latency measured: timed calls per resolution (median; at least 1)")
    parser.add_argument("--latency", default=DEFAULT_PLATFORM, metavar="orin-nano|cpu|FILE|measured",
                        help=f"{LATENCY_HELP}: the reward's compute and latency terms and the load factor rest on "
                             f"it (default {DEFAULT_PLATFORM})")
    parser.add_argument("--optimistic", action="store_true",
                        help="save never-tried actions at their initial value (default: below the state's "
                             "learned values, so exploiting only takes actions it has tried)")
    parser.add_argument("--trace", metavar="STATE",
                        help="also trace every update made in STATE (e.g. bright/still/dense/medium/good/high/rgb) "
                             "and print, per cell of --trace-block, the updates' count and mean reward; "
                             "what is learned does not change")
    parser.add_argument("--trace-block", default="rgb", metavar="SENSOR",
                        help="with --trace: the sensor whose cells are summarized (default rgb)")
    parser.add_argument("--trace-json", type=Path, metavar="FILE",
                        help="with --trace: write every traced update and the summary here")


def _check(args: argparse.Namespace) -> None:
    if args.episodes < 1 or args.seeds < 1:
        raise InputError("--episodes and --seeds: expected at least 1")
    if not 0 < args.min_s <= args.max_s:
        raise InputError(f"--min-s/--max-s: expected 0 < min <= max, got {args.min_s}, {args.max_s}")
    if args.trace_json is not None and args.trace is None:
        raise InputError("--trace-json: only with --trace STATE")


def _check_outputs(args: argparse.Namespace) -> None:
    """The table, its curve and the outcome cache can be written: the table is saved only once an
    episode is trained, so a path that cannot take it must stop the command before the detector loads."""
    from respecd.control.persist import resolve_state_dir

    if args.out is None:  # the table goes into the state directory (save_table makes it)
        check_output_dir("--state-dir", resolve_state_dir(args.state_dir))
    check_output_file("--out", args.out, example="qtable.npz")  # save_table makes the folders
    check_output_file("--curve", args.curve, example="curve.png")  # save_curve makes the folders
    if not args.no_cache:
        check_output_dir("--cache-dir", args.cache_dir)  # OutcomeCache makes the folders
    check_output_file("--trace-json", args.trace_json, example="trace.json")  # written after the training


def main(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from respecd.config import load_profile
    from respecd.control.persist import load_into, read_table, resolve_state_dir, save_table, table_path
    from respecd.lab.experiment import latency as lat
    from respecd.lab.experiment import platforms
    from respecd.lab.experiment.rollout import Piece, Rollout, controller_for
    from respecd.lab.experiment.setup import load_detector, make_evaluator, rgb_resolutions
    from respecd.lab.experiment.training import TrainSettings, conservative, save_curve, train

    _check(args)
    _check_outputs(args)
    profile = load_profile(args.profile)
    out = args.out or table_path(resolve_state_dir(args.state_dir), profile.controller.table_file, profile.name)
    check_output_file("--out" if args.out else "--state-dir", out, example="qtable.npz")  # the table's own name
    check_output_file("--curve", args.curve or out.with_suffix(".curve.png"))
    probe = controller_for(profile, "learn")
    tracer = None
    if args.trace is not None:  # a state or block that is not one is refused before the detector loads
        from respecd.lab.experiment.trace import tracer_for

        tracer = tracer_for(probe.table, probe, args.trace, args.trace_block)
    pinned = platforms.pinned(args.latency, rgb_resolutions(probe))  # a bad file fails first
    detector = load_detector(profile, args.weights, args.random_detector)
    evaluator = make_evaluator(detector, profile, not args.no_cache, args.cache_dir)
    rollout = Rollout(profile, evaluator, {}, args.samples_per_s)
    world = rollout.world(Piece("good-light-static", 0, 10.0))
    rollout.latency = pinned.latency if pinned else lat.measure(
        detector, lat.sim_frames(world, evaluator.inputs), rgb_resolutions(probe), args.latency_repeats)
    latency_ms = lat.to_json(rollout.latency)
    print("latency (ms):", {k: round(v["forward_ms"]) for k, v in latency_ms.items()})
    table = probe.table
    history: list[float] = []
    if args.resume and table is not None and load_into(out, table, probe.layout()):
        history = list(read_table(out)[0].get("episode_reward", []))
        print(f"resuming from {out} ({table.updates} updates, {len(history)} episodes, epsilon {table.epsilon:.3f})")
    settings = TrainSettings(args.episodes, args.seeds, args.min_s, args.max_s, args.seed, args.max_minutes)
    bar = tqdm(total=args.episodes, desc="train-policy", unit="episode", disable=not sys.stderr.isatty())

    def progress(episode: int, result: Any) -> None:
        cache = evaluator.cache
        total = max(1, cache.hits + cache.misses)
        bar.set_postfix(reward=f"{result.episode_reward[-1]:.3f}", eps=f"{result.table.epsilon:.3f}",
                        hit=f"{cache.hits / total:.0%}")
        bar.update()
        save_table(out, result.table, result.layout, _info(profile, args, result, evaluator, latency_ms))

    try:
        result = train(profile, rollout, settings, table, progress, history)
    finally:
        bar.close()
        evaluator.cache.close()
    info = _info(profile, args, result, evaluator, latency_ms)
    if not args.optimistic:
        info["conservative_fill"] = conservative(result.table, 0 if probe.space.mode == "moves" else None)
    save_table(out, result.table, result.layout, info)
    curve = save_curve(result, args.curve or out.with_suffix(".curve.png"))
    print(f"table: {out} ({result.table.updates} updates, {len(result.episode_reward)} episodes, "
          f"{result.seconds:.0f} s, detector {evaluator.inference_s:.0f} s)")
    print(f"learning curve: {curve}")
    if tracer is not None:
        from respecd.lab.experiment.trace import print_and_write

        print_and_write(tracer, args.trace_json)
    return 0


def _info(profile: Profile, args: argparse.Namespace, result: Any, evaluator: Any, latency_ms: dict[str, Any]) -> dict:
    return {"profile": profile.name, "policy": "learn", "trainer": "respecd train-policy",
            "episodes": len(result.episode_reward), "decisions": result.decisions,
            "episode_reward": [round(r, 5) for r in result.episode_reward],
            "detector_fingerprint": evaluator.fingerprint, "seeds": args.seeds, "seed": args.seed,
            "weights": args.weights or profile.perception.weights,
            "latency_ms": latency_ms, "latency_source": str(args.latency)}
