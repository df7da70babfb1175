"""The client's errors (no ROS import): every one a :class:`ClientError` whose ``str()`` is one
line.

A node's refusal carries a machine-readable reason code (:mod:`afm_ros.core.refusals`) that
:func:`refusal` maps to the exception type: :class:`NotEngaged` for ``not_engaged``, else
:class:`Refused`; the words are the node's own.
"""

from __future__ import annotations

import difflib

from afm_ros.core import refusals


class ClientError(Exception):
    """Base of the errors of this module; ``str()`` is one line for a person."""


class NodeNotFound(ClientError):
    """Node ``name`` (None: any node) was not discovered in ``namespace`` within ``timeout`` s.

    ``present``: the nodes that were there; ``elsewhere``: for a named node, the nodes of that name
    in other namespaces; for any node, the namespaces that have nodes (a wrong namespace is the
    usual cause)."""

    def __init__(
        self,
        name: str | None,
        namespace: str,
        timeout: float,
        present: list[str] = (),
        elsewhere: list[str] = (),
    ):
        self.name, self.namespace, self.timeout = name, namespace, timeout
        self.present, self.elsewhere = list(present), list(elsewhere)
        if name is None:
            text = f"no node found in namespace {namespace} within {timeout:g} s"
            if self.elsewhere:
                text += f"; there are nodes in {', '.join(self.elsewhere)}"
        else:
            text = f"node {name} not found within {timeout:g} s"
            text += (
                f" (nodes in {namespace}: {', '.join(self.present)})"
                if self.present
                else f" (no nodes in {namespace})"
            )
            if self.elsewhere:
                text += f"; found as {', '.join(self.elsewhere)}"
        super().__init__(text)


class NoAnswer(ClientError, TimeoutError):
    """``what`` (a service, a node's answer) did not come within ``timeout`` seconds."""

    def __init__(self, what: str, timeout: float):
        self.what, self.timeout = what, timeout
        super().__init__(f"{what} did not answer within {timeout:g} s")


class UnknownParameter(ClientError):
    """``node`` has no parameter ``name``; ``known`` lists the ones it has."""

    def __init__(self, node: str, name: str, known: list[str] = ()):
        self.node, self.name, self.known = node, name, list(known)
        close = difflib.get_close_matches(name, self.known, n=3)
        hint = f"; did you mean {' or '.join(close)}?" if close else ""
        super().__init__(f"{node} has no parameter '{name}'{hint}")


class ParameterRefused(ClientError):
    """``node`` refused to set ``names``; ``reason`` is the node's own (it names the field and the
    allowed range). The node keeps its old values."""

    def __init__(self, node: str, names: list[str], reason: str):
        self.node, self.names, self.reason = node, list(names), reason
        super().__init__(f"{node} refused {', '.join(self.names)}: {reason}")


class ServiceFailed(ClientError):
    """A service answered ``success: false``; ``message`` is its reason."""

    def __init__(self, service: str, message: str):
        self.service, self.message = service, message
        super().__init__(f"{service} refused: {message}")


class Interrupted(KeyboardInterrupt):
    """The caller's ``interrupted()`` said stop (e.g. Ctrl-C) while waiting."""


class Refused(ClientError):
    """The instrument refused a setting or an action; ``reason`` is the node's own words, ``code``
    why (:mod:`afm_ros.core.refusals`: not_engaged, engaged, busy, scanning, not_ready, bad_value,
    internal)."""

    def __init__(self, what: str, reason: str, code: str = refusals.BAD_VALUE):
        super().__init__(f"{what}: {reason}")
        self.what, self.reason, self.code = what, reason, code


class NotEngaged(Refused):
    """An action that needs the tip on the surface (a scan, a spectroscopy) while the z stage is
    not engaged."""


class WorkflowFailed(ClientError):
    """A workflow step (tune, approach, withdraw) ended without reaching its goal; the message says
    why."""


class BadArgument(ClientError, ValueError):
    """A verb's argument of the wrong type or out of its range (checked before anything is sent);
    the message names the argument and what is allowed."""


class LongWork(UserWarning):
    """A verb whose work will take more than a minute of wall time (or a GB): said before it
    starts, with the estimate (simulated time and the wall time per simulated second measured so
    far)."""


def refusal(what: str, reason) -> Refused:
    """The exception for a refusal of ``what``: ``reason`` is a node's message (``[code] text``,
    see :mod:`afm_ros.core.refusals`) or a core's exception (a Refusal carries its code, another
    ValueError is a bad value); :class:`NotEngaged` for not_engaged, else :class:`Refused`."""
    if isinstance(reason, BaseException):
        code, text = refusals.code_of(reason), str(reason)
    else:
        code, text = refusals.parse(reason)
        code = code or refusals.BAD_VALUE
    return (NotEngaged if code == refusals.NOT_ENGAGED else Refused)(what, text, code)
