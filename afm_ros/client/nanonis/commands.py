"""The Nanonis commands the server answers: each declared once with its wire signature (argument
and return field codes, :mod:`afm_ros.formats.nanonis_wire`) beside the function that maps it onto
the instrument (:class:`Session`, over :class:`afm_ros.client.Microscope`).

A handler takes the session and the decoded arguments by name and returns the return values in
order (a tuple; nothing for a command without return values). What it refuses it raises: a client
error (the node's own reason, naming the field and its range), a ValueError (a value outside what
the command allows) or :class:`Unsupported` (a command or mode the emulator does not model); the
dispatcher answers with the error section ``<command>: <reason>`` and the connection goes on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from afm_ros.client.errors import ClientError
from afm_ros.formats.nanonis_catalog import empty_fields
from afm_ros.formats.nanonis_wire import WireError, decode, encode, response


class Unsupported(ValueError):
    """A command, an option or a mode the emulator does not model; ``str()`` says why."""


@dataclass(frozen=True)
class Command:
    """One command: its wire ``name``, argument and return fields ((name, code) pairs), from which
    argument on the request may end early (clients that send a shorter form), and the handler."""

    name: str
    args: tuple
    returns: tuple
    optional_from: int | None
    handler: Callable


COMMANDS: dict[str, Command] = {}


def command(name: str, args=(), returns=(), optional_from: int | None = None):
    """Declare ``name`` with its fields; the decorated function handles it."""

    def register(fn):
        if name in COMMANDS:
            raise ValueError(f"{name} is declared twice")
        COMMANDS[name] = Command(name, tuple(args), tuple(returns), optional_from, fn)
        return fn

    return register


def supported() -> list[str]:
    """The names of every command the server answers, sorted."""
    return sorted(COMMANDS)


def dispatch(session, name: str, body: bytes) -> bytes:
    """The whole response to request ``name`` with ``body``: its return values and an empty
    error section, or no return values and the error section saying why."""
    cmd = COMMANDS.get(name)
    if cmd is None:
        modules = sorted({n.split(".")[0] for n in COMMANDS})
        known = empty_fields(name)
        why = (
            "a Nanonis command this emulator does not model"
            if known is not None
            else "not a command of this emulator"
        )
        return response(
            name,
            known or b"",
            error=f"{name}: {why} (afm_ros answers {len(COMMANDS)} commands of the modules "
            f"{', '.join(modules)}; docs/nanonis.md lists them)",
        )
    try:
        args = decode(cmd.args, body, cmd.optional_from)
    except WireError as exc:
        return _failed(cmd, f"malformed arguments: {exc}")
    try:
        values = cmd.handler(session, **args)
    except (ClientError, ValueError, TimeoutError, RuntimeError) as exc:
        return _failed(cmd, _one_line(exc))
    except Exception as exc:  # a fault of the emulator's own: this command fails, not the server
        session.log("error", f"{name}: internal error: {exc!r}")
        return _failed(cmd, f"internal error of the emulator: {_one_line(exc)}")
    values = () if values is None else values
    try:
        return response(name, encode(cmd.returns, values))
    except WireError as exc:  # a value the wire cannot carry: say so, never a broken frame
        return _failed(cmd, f"the answer cannot be encoded: {exc}")


def _failed(cmd: Command, reason: str) -> bytes:
    """An error response the clients can parse: every return field empty or zero (the clients
    read the fields before the error section), then the error section with ``reason``."""
    empty = [EMPTY[code] for _, code in cmd.returns]
    return response(cmd.name, encode(cmd.returns, empty), error=f"{cmd.name}: {reason}")


# the value of each field code in an error response
EMPTY = {
    "H": 0, "h": 0, "I": 0, "i": 0, "f": 0.0, "d": 0.0, "str": "", "strarr": [],
    "i[]": [], "f[]": [], "d[]": [], "f2d": np.zeros((0, 0)), "str2d": [],
}  # fmt: skip


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def flag(name: str, value: int, allowed: tuple = (0, 1)) -> int:
    """An enumerated argument checked against ``allowed``; ValueError naming it otherwise."""
    if value not in allowed:
        raise ValueError(f"{name}={value}: allowed {', '.join(str(a) for a in allowed)}")
    return value


def finite(name: str, value: float, unit: str = "") -> float:
    if not math.isfinite(value):
        raise ValueError(f"{name}={value} {unit}: must be a finite number".replace("  ", " "))
    return float(value)


def timeout_s(value_ms: int) -> float | None:
    """A Nanonis timeout [ms] as seconds; -1 (wait for ever) as None."""
    if value_ms == -1:
        return None
    if value_ms < 0:
        raise ValueError(f"timeout={value_ms} ms: -1 (no limit) or >= 0")
    return value_ms / 1000.0


TYPES = {
    "H": "uint16",
    "h": "int16",
    "I": "uint32",
    "i": "int32",
    "f": "float32",
    "d": "float64",
    "str": "string",
    "strarr": "string array",
    "i[]": "int32 array",
    "f[]": "float32 array",
    "d[]": "float64 array",
    "f2d": "2D float32",
    "str2d": "2D string",
}


def describe(cmd: Command) -> str:
    """What a command does, in one paragraph (its handler's docstring; a Get without one reads
    back what its Set sets)."""
    doc = cmd.handler.__doc__
    if doc:
        return " ".join(doc.split())
    setter = cmd.name[:-3] + "Set" if cmd.name.endswith("Get") else ""
    if setter in COMMANDS:
        return f"What {setter} sets, read back."
    return ""


def command_table() -> str:
    """The Markdown table of every command (docs/nanonis.md): wire name, arguments and return
    values with their wire types, what it does. Generated from :data:`COMMANDS`."""

    def fields(items) -> str:
        return ", ".join(f"{name} ({TYPES[code]})" for name, code in items) or "-"

    rows = ["| command | arguments | returns | what it does |", "|---|---|---|---|"]
    for name in supported():
        cmd = COMMANDS[name]
        text = describe(cmd).replace("|", "\\|")
        rows.append(f"| `{name}` | {fields(cmd.args)} | {fields(cmd.returns)} | {text} |")
    return "\n".join(rows) + "\n"
