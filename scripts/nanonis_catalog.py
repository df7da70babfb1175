"""Write afm_ros/formats/nanonis_catalog.json: every command of SPECS' nanonis_spm client (the
installed, pinned release) with the response fields it reads, in its own type codes.

The server answers a Nanonis command it does not model with these fields empty (zeros, empty
strings and arrays) and an error section that says why, so every client parses the refusal instead
of misreading the error text as data (afspm's getters, nanonisTCP). Run it after changing the
pinned nanonis-spm; test/test_nanonis_catalog.py checks the file against the installed client.

    .venv/bin/python scripts/nanonis_catalog.py
"""

from __future__ import annotations

import inspect
import json
import sys
from importlib.metadata import version
from pathlib import Path

from nanonis_spm import Nanonis

OUT = Path(__file__).resolve().parents[1] / "afm_ros" / "formats" / "nanonis_catalog.json"


def catalog() -> dict:
    """{command: [response codes]} as nanonis_spm's methods ask for them."""
    seen: dict[str, list[str]] = {}

    class Recorder(Nanonis):
        def __init__(self):  # no connection: quickSend only records
            pass

        def quickSend(self, command, body, body_types, response_types):  # noqa: N802 - theirs
            seen[command] = list(response_types)
            return None

    client = Recorder()
    for name, method in inspect.getmembers(Nanonis, inspect.isfunction):
        if "_" not in name or name.startswith("_") or name[0].islower():
            continue
        arity = len(inspect.signature(method).parameters) - 1
        try:
            getattr(client, name)(*([0] * arity))
        except Exception:  # noqa: BLE001 - a method that converts its arguments first
            try:
                getattr(client, name)(*([[0]] * arity))
            except Exception:  # noqa: BLE001
                print(f"skipped {name}", file=sys.stderr)
    return seen


def main() -> int:
    commands = catalog()
    data = {
        "source": (
            f"nanonis_spm {version('nanonis_spm')} (MIT License, Copyright (c) 2024 Samuel "
            "O'Neill): the response fields its methods read, in its type codes"
        ),
        "commands": dict(sorted(commands.items())),
    }
    lines = [f"{json.dumps(k)}: {json.dumps(v)}" for k, v in data["commands"].items()]
    OUT.write_text(
        "{\n"
        + f'"source": {json.dumps(data["source"])},\n"commands": {{\n'
        + ",\n".join(lines)
        + "\n}\n}\n"
    )
    print(f"{len(commands)} commands -> {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
