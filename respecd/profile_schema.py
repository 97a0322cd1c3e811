"""The profile's JSON Schema, and checking a file as written against it.

The schema is what an editor (yaml-language-server) sees: the ``Profile`` model's keys, plus
``extends:``. A file with ``extends:`` is an overlay and needs no key at all (every section's
keys are optional, lists are replaced whole so a list's items stay complete); one without it
needs ``name`` and ``sensors``. ``check_file`` validates one file against exactly this schema,
with ``FILE:LINE`` for each problem; ``read_profile`` (``respecd check-config``) resolves
``extends:`` and validates the whole profile.
"""

from __future__ import annotations

import json
from typing import Any

from respecd.config import Profile
from respecd.profile_overlay import EXTENDS, nearest, read_source
from respecd.profile_yaml import KeyPath, parse

EXTENDS_SCHEMA = {
    "type": "string",
    "minLength": 1,
    "description": "This file is an overlay of another profile: builtin:NAME or a path relative to this file. "
    "Its keys are merged into the base's: mappings key by key, anything else (a list, a value) replaced whole.",
}

Problem = tuple[KeyPath, str]


def json_schema() -> dict[str, Any]:
    """The schema of a whole profile or an overlay (draft 2020-12)."""
    schema = Profile.model_json_schema()
    whole: dict[str, Any] = {"required": schema.pop("required"), "properties": {}}
    _Partial(schema["$defs"]).sections(schema["properties"], whole["properties"])
    schema["properties"] = {EXTENDS: EXTENDS_SCHEMA, **schema["properties"]}
    schema["if"] = {"required": [EXTENDS]}  # an overlay: nothing else is required
    schema["else"] = whole  # a whole profile: the required keys, and whole mappings where they have some
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "respecd profile"
    schema["description"] = "A respecd profile, or an overlay of one (extends: names its base)."
    return schema


class _Partial:
    """Overlay variants (``NameOverlay``) of the definitions an overlay reaches through mappings
    and that require a key, themselves or below: merged key by key, an overlay's mapping may
    leave any key to its base. Lists are replaced whole, so what a list holds stays whole."""

    def __init__(self, defs: dict[str, Any]) -> None:
        self.defs = defs

    def sections(self, properties: dict[str, Any], whole: dict[str, Any]) -> None:
        """Point ``properties`` at overlay variants; ``whole`` gets the full ones back."""
        for key, node in properties.items():
            full = json.dumps(node)
            self._retarget(node)
            if json.dumps(node) != full:
                whole[key] = json.loads(full)

    def _retarget(self, node: dict[str, Any]) -> None:
        for option in (node, *node.get("anyOf", ())):
            if "$ref" in option:
                option["$ref"] = self._variant(option["$ref"].rsplit("/", 1)[1])

    def _variant(self, name: str) -> str:
        if not self._needs(name):
            return f"#/$defs/{name}"
        overlay = f"{name}Overlay"
        if overlay not in self.defs:
            definition = json.loads(json.dumps(self.defs[name]))
            definition.pop("required", None)
            for child in definition.get("properties", {}).values():
                self._retarget(child)
            self.defs[overlay] = definition
        return f"#/$defs/{overlay}"

    def _needs(self, name: str) -> bool:
        definition = self.defs[name]
        children = [option["$ref"].rsplit("/", 1)[1] for node in definition.get("properties", {}).values()
                    for option in (node, *node.get("anyOf", ())) if "$ref" in option]
        return bool(definition.get("required")) or any(self._needs(child) for child in children)


def check_file(source: str) -> list[str]:
    """Every way the file ``source`` (or ``builtin:NAME``) breaks the schema, as ``FILE:LINE: path: message``.

    Raises ConfigError when the file cannot be read or is not YAML."""
    from jsonschema import Draft202012Validator

    _, label, text = read_source(source)
    parsed = parse(label, text)
    document = json.loads(json.dumps(parsed.document, default=str))  # as read_profile sees it
    origins = {path: (label, line) for path, line in parsed.lines.items()}
    problems = []
    for error in Draft202012Validator(json_schema()).iter_errors(document):
        for path, message in _explain(error):
            where, line = nearest(origins, path, (label, 1))
            problems.append((line, f"{where}:{line}: {'.'.join(map(str, path)) or '(top level)'}: {message}"))
    return [text for _, text in sorted(set(problems))]  # by line, then path; a key missing once


def _explain(error: Any) -> list[Problem]:
    """The problems behind one jsonschema error, at the key they are about."""
    path = tuple(error.absolute_path)
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        known = error.schema.get("properties", {})
        return [((*path, key), "unknown key (check the spelling; `respecd schema` lists the valid keys)")
                for key in error.instance if key not in known]
    if error.validator == "required" and isinstance(error.instance, dict):
        return [((*path, key), "required key is missing") for key in error.validator_value if key not in error.instance]
    mapping = error.schema.get("discriminator", {}).get("mapping") if error.validator == "oneOf" else None
    if not mapping or not isinstance(error.instance, dict):
        return [(path, error.message)]
    tag = error.instance.get("driver")  # a sensor entry: explain it as its own driver's entry
    if tag not in mapping:
        return [((*path, "driver"), f"unknown driver {tag!r} (expected one of: {', '.join(sorted(mapping))})")]
    branch = next(i for i, option in enumerate(error.schema["oneOf"]) if option.get("$ref") == mapping[tag])
    return [problem for sub in error.context if sub.relative_schema_path[0] == branch for problem in _explain(sub)]
