"""Checks of a valid profile against this machine, before anything starts: the files it
names exist, the torch device it asks for is usable, the state directory is writable.

``load_profile`` only says whether a profile is well-formed; these say whether it can run
here. ``respecd check-config`` and the daemon run the same checks, so a profile that
check-config calls ok does not die at start. Every problem is one ``FILE:LINE: path: ...``
line (exit 2).

Why an unusable torch device is an error and not a fallback to the CPU: the profile asked
for that device, and on the rover the detector on the CPU is several times slower, so the
controller's latency and load signals, and the Q-table learned from them, would silently
describe another machine. Write ``device: cpu`` to run on the CPU.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from respecd import filekind, pathkind
from respecd.config import LoadedProfile
from respecd.drivers.uvc import UVCConfig
from respecd.errors import ConfigError
from respecd.perception.config import BUILTIN_PREFIX, resolve_weights

NOT_A_DEVICE = "is not a torch device"


def check_profile(loaded: LoadedProfile, state_dir: Path | None = None, policy: str | None = None,
                  create_state_dir: bool = False, record: str | None = None) -> list[str]:
    """Every problem that would stop this profile from running on this machine. The daemon
    creates a missing state directory (``create_state_dir``); check-config only asks whether
    it could. ``record``: the daemon's ``--record``, which replaces ``recording.path`` (and is
    checked as a flag)."""
    problems = [*_weights(loaded), *_replay_sensors(loaded), *_sensor_files(loaded),
                *_qtable(loaded, state_dir, policy)]
    if record is None:
        problems += _recording(loaded)
    profile = loaded.model
    if profile.perception.enabled:
        problems += _perception_device(loaded)
    return problems + _learning_state_dir(loaded, state_dir, policy, create_state_dir)


def check_portable(loaded: LoadedProfile) -> tuple[list[str], list[str]]:
    """(problems, skipped): what a profile needs wherever it is checked, and the checks of this
    machine left out (the torch device, files that live on the robot, the state directory), each
    with what it would say here. For a profile studied away from its robot (``check-config
    --portable``); a built-in checkpoint ships in the package and is checked everywhere."""
    perception = loaded.model.perception
    local_weights = perception.enabled and not perception.weights.startswith(BUILTIN_PREFIX)
    problems = [*_replay_sensors(loaded)]
    skipped = []
    if local_weights and not resolve_weights(perception.weights).exists():
        skipped.append(f"perception.weights: {perception.weights} (not on this machine)")
    else:
        problems += _weights(loaded)
    if perception.enabled:
        typo, here = _portable_device(loaded)
        problems += typo
        skipped.append(f"perception.device: {perception.device!r}" + (f" (here: {here})" if here else ""))
    for line in _sensor_files(loaded):
        skipped.append(f"sensor file {_unlocated(line)}")
    if loaded.model.recording.enabled:
        found = [f" (here: {_unlocated(line)})" for line in _recording(loaded)]
        skipped.append(f"recording.path: {loaded.model.recording.path}{''.join(found)}")
    if loaded.model.controller.enabled:
        skipped.append("the state directory and its Q-table")
    return problems, skipped


def _portable_device(loaded: LoadedProfile) -> tuple[list[str], str | None]:
    """(a device no machine has: the profile's problem, what this machine says of the device). A
    device the runtime never names (``cdua``) is wrong on the robot too; one this machine lacks is not."""
    perception = loaded.model.perception
    if perception.runtime == "torch":
        here = device_problem(perception.device)
        typo = here is not None and NOT_A_DEVICE in here
    else:
        from respecd.perception import runtimes

        try:
            runtimes.backend(perception.runtime).parse_device(perception.device)
        except ConfigError as err:
            return [_at(loaded, ("perception", "device"), str(err).removeprefix("perception.device: "))], None
        here, typo = runtimes.problem(perception), False
    return ([_at(loaded, ("perception", "device"), str(here))] if typo else []), here


def _unlocated(line: str) -> str:
    """A problem line without its ``FILE:LINE: `` prefix."""
    parts = line.split(": ", 1)
    return parts[1] if len(parts) == 2 and ":" in parts[0] else line


def check_state_dir(path: Path, create: bool = True) -> str | None:
    """Why ``path`` cannot hold the Q-table, or None. A real write is tried: permissions alone do
    not show a read-only mount or a full disk. Without ``create`` (check-config) the folders made
    for the try are removed again, so asking leaves nothing behind."""
    if path.exists() and not path.is_dir():
        kind = pathkind.describe(path.stat().st_mode)
        return f"{path}: is {kind}, not a directory; the state directory holds the Q-table"
    from respecd.outputs import write_error

    err = write_error(path, keep=create)
    if err is not None:
        return f"{path}: state directory is not writable ({err.strerror or err}); the Q-table could not be saved"
    return None


def learns(loaded: LoadedProfile, policy: str | None) -> bool:
    """Whether the daemon will learn (and so write its Q-table): ``policy`` is ``--policy``."""
    controller = loaded.model.controller
    return controller.enabled and (policy or controller.policy) == "learn"


def _learning_state_dir(loaded: LoadedProfile, state_dir: Path | None, policy: str | None,
                        create: bool) -> list[str]:
    """A learning daemon saves its Q-table in the state directory, so it must be writable at start."""
    if state_dir is None or not learns(loaded, policy):
        return []
    problem = check_state_dir(state_dir, create)
    return [f"--state-dir: {problem}"] if problem else []


def _recording(loaded: LoadedProfile) -> list[str]:
    """A recording profile must be able to open its file at start: the recorder would pause at its
    first write (blaming the disk) and the session would go unrecorded."""
    from respecd.outputs import recording_problem

    recording = loaded.model.recording
    if not recording.enabled:
        return []
    problem = recording_problem(recording.path)
    return [_at(loaded, ("recording", "path"), problem)] if problem else []


def _perception_device(loaded: LoadedProfile) -> list[str]:
    """The device (runtime torch), or the runtime with its device and precision, this machine cannot run."""
    perception = loaded.model.perception
    if perception.runtime == "torch":
        reason = device_problem(perception.device)
        return [_at(loaded, ("perception", "device"), reason)] if reason else []
    from respecd.perception import runtimes

    reason = runtimes.problem(perception)
    return [_at(loaded, ("perception", "runtime"), reason)] if reason else []


def device_problem(device: str) -> str | None:
    """Why this torch cannot run on ``device``, or None. Imports torch only for a non-CPU device."""
    if device == "cpu":
        return None
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError) as err:
        return f"{device!r} {NOT_A_DEVICE} ({err}); expected cpu, cuda or cuda:N"
    if parsed.type == "cpu":
        return None
    if parsed.type == "cuda":
        if torch.version.cuda is None:
            return (f"{device!r} cannot be used: this torch ({torch.__version__}) was built without CUDA "
                    "(install a CUDA build, e.g. the Jetson wheel via TORCH_SPEC, or write device: cpu)")
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            return f"{device!r} cannot be used: torch {torch.__version__} sees no CUDA device (driver loaded?)"
        if parsed.index is not None and parsed.index >= count:
            return f"{device!r} cannot be used: this machine has {count} CUDA device(s)"
        return None
    backend = getattr(torch.backends, parsed.type, None) or getattr(torch, parsed.type, None)
    available = getattr(backend, "is_available", None)
    if available is None or not available():
        return f"{device!r} cannot be used by this torch ({torch.__version__}); expected cpu or cuda"
    return None


def _at(loaded: LoadedProfile, path: tuple[Any, ...], message: str) -> str:
    return f"{loaded.where(*path)}: {'.'.join(map(str, path))}: {message}"


def _weights(loaded: LoadedProfile) -> list[str]:
    perception = loaded.model.perception
    if not perception.enabled:
        return []
    try:
        path = resolve_weights(perception.weights)
    except ConfigError as err:
        return [_at(loaded, ("perception", "weights"), str(err))]
    if path.is_dir():
        return [_at(loaded, ("perception", "weights"), f"{path}: is a directory, expected a checkpoint file")]
    if not path.is_file():
        return [_at(loaded, ("perception", "weights"), f"{path}: no such checkpoint file")]
    try:
        head = filekind.read_head(path)
    except OSError as err:
        return [_at(loaded, ("perception", "weights"), f"{path}: cannot read checkpoint: {err.strerror or err}")]
    if not head.startswith(filekind.ZIP_MAGIC) and not filekind.is_pickle(head):  # torch's formats
        return [_at(loaded, ("perception", "weights"), f"{path}: not a torch checkpoint: it looks like "
                    f"{filekind.describe(head, path)}; expected a respecd checkpoint written by `respecd train` "
                    "(a torch zip archive)")]
    return []


def _replay_sensors(loaded: LoadedProfile) -> list[str]:
    """A ``replay`` sensor serves frames of an opened log: only ``respecd --replay LOG`` has one
    (and builds its own replay sensors from the profile). Live, it could never start."""
    return [
        _at(loaded, ("sensors", i, "driver"),
            "driver 'replay' serves a recorded log and works only under `respecd --replay LOG`, which swaps "
            "every sensor of the profile for a replay sensor itself; for a live run name a device driver "
            "(sim, uvc, flirone, iwr6843, realsense)")
        for i, sensor in enumerate(loaded.model.sensors)
        if sensor.driver == "replay"
    ]


def _sensor_files(loaded: LoadedProfile) -> list[str]:
    """Files a sensor entry names: any path-typed key, and a video file played as a camera."""
    problems = []
    for i, sensor in enumerate(loaded.model.sensors):
        for key in type(sensor).model_fields:
            value = getattr(sensor, key)
            if isinstance(value, Path) and not value.is_file():
                problems.append(_at(loaded, ("sensors", i, key), f"{value}: no such file"))
        if isinstance(sensor, UVCConfig) and sensor.is_file and not Path(str(sensor.device)).is_file():
            problems.append(_at(loaded, ("sensors", i, "device"), f"{sensor.device}: no such video file"))
    return problems


def _qtable(loaded: LoadedProfile, state_dir: Path | None, policy: str | None) -> list[str]:
    """The table a learning or exploiting controller reads must be a file (a FIFO would hang the
    load, a directory is no table); a frozen policy (exploit) with a named table needs that table."""
    from respecd.control.persist import EXPECTED_SHORT, table_path
    from respecd.control.statelock import LOCK_NAME

    controller = loaded.model.controller
    chosen = policy or controller.policy
    if not controller.enabled or chosen not in ("learn", "exploit") or state_dir is None:
        return []
    path = table_path(state_dir, controller.table_file, loaded.model.name)

    def named(problem: str) -> str:  # the profile's table_file, else the state directory's own name for it
        if controller.table_file:
            return _at(loaded, ("controller", "table_file"), problem)
        if pathkind.name_problem(path):  # named after the profile: the name is what to change
            return _at(loaded, ("name",), f"{problem}; the Q-table is named after the profile: shorten name "
                       "or set controller.table_file")
        return f"--state-dir: {problem}"

    problems = [named(p) for p in [pathkind.problem(path, EXPECTED_SHORT)] if p]
    if not problems and os.path.exists(path) and not os.access(path, os.R_OK, effective_ids=True):
        problems.append(named(f"{path}: cannot read the Q-table (permission denied); fix its permissions"))
    if chosen == "learn":
        problems += [f"--state-dir: {p}" for p in [pathkind.problem(state_dir / LOCK_NAME, "the daemon's lock file")]
                     if p]
    elif controller.table_file and not problems and not os.path.isfile(path):
        problems.append(named(f"{path}: no such Q-table (policy exploit reads it)"))
    return problems
