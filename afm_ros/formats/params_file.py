"""ROS 2 parameter files (the ``--params-file`` / ``ros2 param dump`` YAML), without ROS.

A file maps node keys to ``{ros__parameters: {name: value}}``; nested maps are dotted names
(``qos_overrides: {a: ...}`` is ``qos_overrides.a``). A key selects nodes by fully qualified
name as rcl does: ``/afm1/z_controller``, ``z_controller`` (= ``/z_controller``), with ``*``
for one namespace level and ``**`` for any number of levels (``/**/z_controller`` matches the
node in every namespace, as ``config/afm.yaml`` does).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from afm_ros.formats import user_files  # doubles that rcl and YAML 1.1 read as doubles

PARAMETERS_KEY = "ros__parameters"


def yaml_value(value) -> str:
    """``value`` as YAML text that rcl and YAML 1.1 (PyYAML) read back as the same type: doubles
    keep a '.' and a signed exponent, strings are single-quoted."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)
        if "e" in text:
            mantissa, exponent = text.split("e")
            if "." not in mantissa:
                mantissa += ".0"
            if exponent[0] not in "+-":
                exponent = "+" + exponent
            return f"{mantissa}e{exponent}"
        return text if "." in text else text + ".0"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


class ParamsFileError(user_files.UserFileError):
    """A parameter file that cannot be used; the message names the file and what is wrong."""


def key_matches(key: str, fqn: str) -> bool:
    """True if the params-file node key ``key`` selects the node ``fqn`` (``/ns/name``)."""
    if not key.startswith("/"):
        key = "/" + key
    pattern = ""
    for token in key.strip("/").split("/"):
        if token == "**":
            pattern += r"(?:/[^/]+)*"
        else:
            pattern += "/" + ("[^/]+" if token == "*" else re.escape(token))
    return re.fullmatch(pattern, fqn) is not None


def _flatten(values: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for name, value in values.items():
        full = f"{prefix}{name}"
        if isinstance(value, dict):
            out.update(_flatten(value, full + "."))
        else:
            out[full] = value
    return out


def read(path: str | Path):
    """The parameter file's YAML, bounded in size, depth and aliases
    (:mod:`afm_ros.formats.user_files`); ParamsFileError naming the file."""
    try:
        return user_files.load(path, "parameter file")
    except user_files.UserFileError as exc:
        raise ParamsFileError(str(exc)) from None


def parameters_for(path: str | Path, fqn: str) -> dict[str, Any]:
    """The values ``path`` holds for node ``fqn`` (dotted names), as YAML typed them.

    Keys with wildcards apply first, then the exact key, so the node's own entry wins. Raises
    ParamsFileError naming the file if it cannot be read, is not a parameter file, or has no
    entry for the node.
    """
    content = read(path)
    if not isinstance(content, dict) or not content:
        raise ParamsFileError(
            f"{path} is not a ROS parameter file (expected '<node>: {{{PARAMETERS_KEY}: ...}}')"
        )
    matching = [k for k in content if isinstance(k, str) and key_matches(k, fqn)]
    if not matching:
        raise ParamsFileError(
            f"{path} has no parameters for {fqn} (its node keys: {', '.join(map(str, content))})"
        )
    values: dict[str, Any] = {}
    for key in sorted(
        matching, key=lambda k: "*" not in k
    ):  # wildcards first, the node's own key last
        entry = content[key]
        if not isinstance(entry, dict) or not isinstance(entry.get(PARAMETERS_KEY), dict):
            raise ParamsFileError(f"{path}: '{key}' has no '{PARAMETERS_KEY}' map")
        values.update(_flatten(entry[PARAMETERS_KEY]))
    return values


def dump_text(
    key: str, values: dict[str, Any], comments: dict[str, str] | None = None, header: str = ""
) -> str:
    """A parameter file with ``values`` (dotted names nested) under node key ``key``; each value
    preceded by ``# comments[name]`` if given. Doubles keep a '.' so that YAML reads them back as
    doubles (see :func:`yaml_value`)."""
    lines = [f"# {line}" for line in header.splitlines()] + [f"{key}:", f"  {PARAMETERS_KEY}:"]
    opened: list[str] = []
    for name in sorted(values):
        parts = name.split(".")
        common = 0
        while common < min(len(opened), len(parts) - 1) and opened[common] == parts[common]:
            common += 1
        opened = opened[:common]
        for part in parts[common:-1]:
            lines.append("    " + "  " * len(opened) + f"{part}:")
            opened.append(part)
        indent = "    " + "  " * len(opened)
        if comments and comments.get(name):
            lines.append(f"{indent}# {comments[name]}")
        lines.append(f"{indent}{parts[-1]}: {yaml_value(values[name])}")
    return "\n".join(lines) + "\n"
