"""Reading a profile source (a file or ``builtin:NAME``) and resolving ``extends:``.

An overlay names its base with ``extends: builtin:NAME`` or a path (relative to the overlay's
own file) and writes only what differs. The base is resolved first (chains allowed), then the
overlay is merged into it key by key: mappings merge recursively, anything else the overlay
writes — a scalar, a list, null — replaces the base's value whole. Lists are not merged
item by item because a sensor list or a scenario list means what it says as a whole.

Every value keeps the file and line that wrote it (``origins``), so an error in an inherited
value names the base file, and one in an overridden value names the overlay.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from respecd import pathkind
from respecd.errors import ConfigError, InputError
from respecd.profile_yaml import MAX_BYTES, KeyPath, parse

BUILTIN_PREFIX = "builtin:"
BUILTIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")  # a file name in the package, no path
EXTENDS = "extends"
MAX_CHAIN = 16  # overlays of overlays; far more than a person would write

Origin = tuple[str, int]  # (file label, 1-based line)


@dataclass(frozen=True)
class Resolved:
    """A profile document with every overlay applied, and where each key path was written."""

    document: dict[str, Any]
    origins: dict[KeyPath, Origin]
    label: str  # the file that was asked for (the last overlay)


def resolve(source: str) -> Resolved:
    """Read ``source`` and every base it extends; ConfigError with ``FILE:LINE`` problems."""
    return _resolve(source, chain=(), referrer=None)


def nearest(origins: dict[KeyPath, Origin], path: KeyPath, default: Origin) -> Origin:
    """Where ``path`` (or its closest written ancestor) was written."""
    for cut in range(len(path), -1, -1):
        if path[:cut] in origins:
            return origins[path[:cut]]
    return default


def _resolve(source: str, chain: tuple[str, ...], referrer: Origin | None) -> Resolved:
    try:
        identity, label, text = read_source(source)
    except ConfigError as err:
        if referrer is None:
            raise
        raise ConfigError(_at(referrer, f"{EXTENDS}: {err}")) from err
    if identity in chain:
        cycle = " -> ".join((*chain[chain.index(identity):], identity))
        raise ConfigError(_at(referrer, f"{EXTENDS}: profiles extend each other in a cycle: {cycle}"))
    if len(chain) >= MAX_CHAIN:
        raise ConfigError(_at(referrer, f"{EXTENDS}: more than {MAX_CHAIN} profiles in one chain"))
    parsed = parse(label, text)
    if not isinstance(parsed.document, dict):
        raise ConfigError(f"{label}:1: profile must be a mapping of sections (expected keys like name, sensors)")
    origins = {path: (label, line) for path, line in parsed.lines.items()}
    document = dict(parsed.document)
    if EXTENDS not in document:
        return Resolved(document, origins, label)
    here = origins[(EXTENDS,)]
    base = _resolve(_base_source(document.pop(EXTENDS), label, here), (*chain, identity), here)
    merged_origins = dict(base.origins)
    merged = _merge(base.document, document, merged_origins, origins, ())
    merged_origins[()] = origins.get((), (label, 1))
    return Resolved(merged, merged_origins, label)


def _base_source(reference: Any, label: str, here: Origin) -> str:
    """The base's source: ``builtin:NAME`` as written, a relative path from the overlay's folder."""
    if not isinstance(reference, str) or not reference.strip():
        raise ConfigError(_at(here, f"{EXTENDS}: expected builtin:NAME or a path to a profile, got {reference!r}"))
    if reference.startswith(BUILTIN_PREFIX) or Path(reference).is_absolute():
        return reference
    if label.startswith(f"<{BUILTIN_PREFIX}"):
        raise ConfigError(_at(here, f"{EXTENDS}: a built-in profile extends builtin:NAME, not a path ({reference!r})"))
    return os.path.normpath(Path(label).parent / reference)


def _merge(base: dict[str, Any], overlay: dict[str, Any], origins: dict[KeyPath, Origin],
           overlay_origins: dict[KeyPath, Origin], path: KeyPath) -> dict[str, Any]:
    """``base`` with ``overlay`` applied (new dicts; YAML aliases may share the old ones)."""
    merged = dict(base)
    for key, value in overlay.items():
        at = (*path, key)
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            if at in overlay_origins:
                origins[at] = overlay_origins[at]
            merged[key] = _merge(base[key], value, origins, overlay_origins, at)
            continue
        merged[key] = value
        for written in [p for p in origins if p[: len(at)] == at]:
            del origins[written]
        origins.update((p, o) for p, o in overlay_origins.items() if p[: len(at)] == at)
    return merged


def _at(origin: Origin | None, message: str) -> str:
    return f"{origin[0]}:{origin[1]}: {message}" if origin else message


def read_source(source: str) -> tuple[str, str, str]:
    """``(identity, label, text)`` of a profile: identity is ``builtin:NAME`` or the resolved path."""
    if source.startswith(BUILTIN_PREFIX):
        name = source[len(BUILTIN_PREFIX):]
        resource = resources.files("respecd.profiles") / f"{name}.yaml"  # a mapped package (pyproject package-dir)
        if not BUILTIN_NAME.fullmatch(name) or not resource.is_file():
            raise ConfigError(f"{source}: no built-in profile named {name!r}")
        return source, f"<{source}>", resource.read_text(encoding="utf-8")
    path = Path(source)
    return str(path.resolve()), str(path), _read_file(path)


def _read_file(path: Path) -> str:
    try:
        with pathkind.open_regular(path, "a profile (a YAML file)") as handle:  # a FIFO or a device: at once
            data = handle.read(MAX_BYTES + 1)  # at most one byte past the limit
            size = os.fstat(handle.fileno()).st_size
        if len(data) > MAX_BYTES:
            raise ConfigError(
                f"{path}:1: profile is {size} bytes, more than the {MAX_BYTES} allowed "
                "(a profile is a few kB: is this the right file?)"
            )
        return data.decode("utf-8")
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: no such file") from err
    except IsADirectoryError as err:
        raise ConfigError(f"{path}: is a directory, expected a profile (a YAML file)") from err
    except InputError as err:
        raise ConfigError(str(err)) from err
    except UnicodeDecodeError as err:
        line = err.object[: err.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text: byte {err.start} is {err.object[err.start]:#04x} "
                          "(expected a YAML profile: is this the right file?)") from err
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from err
