"""Reading a profile's YAML safely: bounded in size, nesting and alias expansion, with
duplicate keys as errors and a key-path -> line index for error messages.

A profile is a few kB. YAML aliases let 377 bytes stand for 9^10 values; PyYAML shares the
aliased objects, but anything that walks the document per path (pydantic, a line index)
expands them. So the event stream is scanned first, without building anything, and a
document whose aliases expand past ``MAX_VALUES`` is refused before it is composed; the
line index then visits each node once, whatever number of paths lead to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import yaml

from respecd.errors import ConfigError

MAX_BYTES = 256 * 1024  # the largest shipped profile is 4 kB
MAX_VALUES = 50_000  # scalars + collections after alias expansion (sim-rover: ~400)
MAX_DEPTH = 64  # nesting; also keeps the composer's recursion far from any stack limit
_MERGE_TAG = "tag:yaml.org,2002:merge"
Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: ~4x faster when present

KeyPath = tuple[Any, ...]


@dataclass(frozen=True)
class ParsedYaml:
    document: Any
    lines: dict[KeyPath, int]  # key path -> 1-based line


def parse(label: str, text: str) -> ParsedYaml:
    """Parse one profile document; ConfigError with ``FILE:LINE: ...`` problems otherwise."""
    if len(text) > MAX_BYTES:
        raise ConfigError(
            f"{label}:1: profile is {len(text)} characters, more than the {MAX_BYTES} allowed "
            "(a profile is a few kB: is this the right file?)"
        )
    try:
        scan = _Scan(label)
        for event in yaml.parse(text, Loader=Loader):
            scan.feed(event)
        if scan.problems:
            raise ConfigError(f"{label}: {len(scan.problems)} problem(s)", [p for _, p in sorted(scan.problems)])
        return ParsedYaml(yaml.load(text, Loader=Loader), scan.lines)  # noqa: S506 - a safe loader
    except yaml.reader.ReaderError as err:  # a character YAML never allows; said without pyyaml's "position N"
        line, column = _line_column(text, err.position)
        char = err.character if isinstance(err.character, int) else ord(err.character)
        raise ConfigError(
            f"{label}:{line}: not valid YAML: character U+{char:04X} at column {column}: {err.reason} "
            "(a profile is plain UTF-8 text: is this the right file?)"
        ) from err
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 1  # lines are 1-based; no mark: the document as a whole
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{label}:{line}: not valid YAML: {problem}") from err


def _line_column(text: str, position: int) -> tuple[int, int]:
    """1-based line and column of the character at ``position`` in ``text``."""
    line_start = text.rfind("\n", 0, position) + 1
    return text.count("\n", 0, position) + 1, position - line_start + 1


@dataclass
class _Frame:
    """An open mapping or sequence in the event stream."""

    path: KeyPath
    anchor: str | None
    start: int  # values expanded before this collection
    mapping: bool
    items: int = 0  # sequence items so far
    key: Any = None  # mapping: the key whose value comes next (None: a key comes next)
    keys: dict[str, int] = field(default_factory=dict)  # mapping: key -> line
    skip: bool = False  # a collection used as a key: not indexed


class _Scan:
    """One pass over the events: key path -> line, duplicate keys, depth and alias expansion.

    Nothing is built, so an alias bomb costs its size in events, not its expansion; an
    alias is indexed where it is written and never entered."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.lines: dict[KeyPath, int] = {}
        self.problems: list[tuple[int, str]] = []
        self._stack: list[_Frame] = []
        self._sizes: dict[str, int] = {}  # anchor -> values it stands for
        self._expanded = 0
        self._aliases = 0

    def feed(self, event: yaml.Event) -> None:
        line = event.start_mark.line + 1 if event.start_mark is not None else 1
        if isinstance(event, yaml.CollectionEndEvent):
            self._close(self._stack.pop())
        elif isinstance(event, yaml.AliasEvent):
            self._alias(event, line)
        elif isinstance(event, (yaml.ScalarEvent, yaml.CollectionStartEvent)):
            self._node(event, line)
        if self._expanded > MAX_VALUES:
            how = "aliases expand the profile to" if self._aliases else "the profile holds"
            raise ConfigError(
                f"{self.label}:{line}: {how} more than {MAX_VALUES} values (a profile needs a few hundred)"
            )

    def _alias(self, event: yaml.AliasEvent, line: int) -> None:
        if event.anchor not in self._sizes:
            if any(frame.anchor == event.anchor for frame in self._stack):
                raise ConfigError(f"{self.label}:{line}: alias *{event.anchor} refers to itself (a recursive value)")
            return  # undefined: yaml.load reports it with its line
        self._expanded += self._sizes[event.anchor]
        self._aliases += 1
        self._place(line, is_scalar_key=None)

    def _node(self, event: yaml.NodeEvent, line: int) -> None:
        self._expanded += 1
        scalar = isinstance(event, yaml.ScalarEvent)
        path = self._place(line, is_scalar_key=getattr(event, "value", None) if scalar else None)
        if scalar:
            if event.anchor:
                self._sizes[event.anchor] = 1
            return
        skip = path is None or bool(self._stack and self._stack[-1].skip)
        mapping = isinstance(event, yaml.MappingStartEvent)
        self._stack.append(_Frame(path or (), event.anchor, self._expanded - 1, mapping, skip=skip))
        if len(self._stack) > MAX_DEPTH:
            raise ConfigError(f"{self.label}:{line}: nested more than {MAX_DEPTH} levels deep")

    def _place(self, line: int, is_scalar_key: str | None) -> KeyPath | None:
        """Where the node starting on ``line`` sits: its key path, or None for a mapping key."""
        if not self._stack:
            self.lines.setdefault((), line)
            return ()
        frame = self._stack[-1]
        if not frame.mapping:
            path = (*frame.path, frame.items)
            frame.items += 1
            if not frame.skip:
                self.lines[path] = line
            return path
        if frame.key is None:  # this node is a key
            self._key(frame, is_scalar_key, line)
            return None
        path, frame.key = (*frame.path, frame.key[0]), None
        return path

    def _key(self, frame: _Frame, name: str | None, line: int) -> None:
        if frame.skip:
            frame.key = ("",)
            return
        if name is None:
            self.problems.append((line, f"{self.label}:{line}: {_dotted(frame.path)}: a key must be a plain name"))
            frame.key = ("",)
            return
        frame.key = (name,)
        if name == "<<":  # a merge key: its values may repeat and be overridden
            return
        child = (*frame.path, name)
        if name in frame.keys:
            problem = f"{self.label}:{line}: {_dotted(child)}: duplicate key (first given on line {frame.keys[name]})"
            self.problems.append((line, problem))
            return
        frame.keys[name] = line
        self.lines[child] = line

    def _close(self, frame: _Frame) -> None:
        if frame.anchor:
            self._sizes[frame.anchor] = self._expanded - frame.start


def _dotted(path: KeyPath) -> str:
    return ".".join(str(p) for p in path) or "(top level)"
