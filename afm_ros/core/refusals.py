"""Why a block refused a request, as a code a program can test (no ROS).

A refused service call answers ``success: false`` with a message that starts with the code in
brackets, ``[not_engaged] scan refused: not engaged: the z stage is withdrawn; ...``: the words are
for a person, the code for a program (the client maps it to its exception types; a Nanonis error
section can carry it). The cores raise :class:`Refusal` (a ValueError with a ``code``).
"""

from __future__ import annotations

import re

NOT_ENGAGED = "not_engaged"  # needs the tip on the surface (a scan, a spectroscopy)
ENGAGED = "engaged"  # needs the cantilever free (a tune, a coarse motor move)
BUSY = "busy"  # the same work is running (a tune, an approach, a scan, a spectroscopy)
SCANNING = "scanning"  # needs the tip parked
NOT_READY = "not_ready"  # the node does not know what it needs yet (another node has not spoken)
# a value out of its range, or a request that does not fit (the z range, the rate)
BAD_VALUE = "bad_value"
INTERNAL = "internal"  # an exception in the node's own code (afm_ros.nodes.guard)
CODES = (NOT_ENGAGED, ENGAGED, BUSY, SCANNING, NOT_READY, BAD_VALUE, INTERNAL)

_TAGGED = re.compile(r"\[([a-z_]+)\] (.*)", re.S)


class Refusal(ValueError):
    """A request refused for ``code`` (one of :data:`CODES`); ``str()`` is the reason in words."""

    def __init__(self, code: str, text: str):
        if code not in CODES:
            raise ValueError(f"refusal code {code!r} is not one of {', '.join(CODES)}")
        super().__init__(text)
        self.code = code


def code_of(exc: BaseException) -> str:
    """The code of an exception a core raised: a Refusal's own, else BAD_VALUE (a ValueError names
    a value)."""
    return exc.code if isinstance(exc, Refusal) else BAD_VALUE


def tagged(code: str, text: str) -> str:
    """A refusal message: ``[code] text``."""
    if code not in CODES:
        raise ValueError(f"refusal code {code!r} is not one of {', '.join(CODES)}")
    return f"[{code}] {text}"


def parse(message: str) -> tuple[str | None, str]:
    """(code, text) of a refusal message; (None, message) if it carries no code."""
    m = _TAGGED.fullmatch(message or "")
    return (m[1], m[2]) if m and m[1] in CODES else (None, message)
