"""Every command of the Nanonis programming interface with the response fields SPECS' client
reads (``nanonis_catalog.json``, generated from nanonis_spm by scripts/nanonis_catalog.py), so a
command the emulator does not model is still answered in the layout clients parse: its fields empty
(zeros, empty strings and arrays), then the error section saying why (no ROS)."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

CATALOG = Path(__file__).with_name("nanonis_catalog.json")
# bytes of a zero of each scalar code; every other code (strings, arrays, 2D arrays) is an
# element list whose count, a zero scalar before it, makes it empty
SCALAR_BYTES = {"H": 2, "h": 2, "I": 4, "i": 4, "f": 4, "d": 8}


@lru_cache(maxsize=1)
def commands() -> dict[str, list[str]]:
    """{command name: response codes in nanonis_spm's notation}."""
    return json.loads(CATALOG.read_text())["commands"]


def empty_fields(name: str) -> bytes | None:
    """The response fields of ``name`` with every value empty; None for a name not in the
    catalog."""
    codes = commands().get(name)
    if codes is None:
        return None
    return bytes(sum(SCALAR_BYTES.get(code, 0) for code in codes))
