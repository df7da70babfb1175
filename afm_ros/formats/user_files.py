"""Reading files a user hands over (parameter files, dataset specs, sample descriptions), bounded.

Every parser of a user file goes through here, so a hostile or broken file costs at most a
bounded read and one line of error, never memory, a deep recursion or a traceback:

- size: at most ``max_bytes`` are read (the file's size is checked first);
- text: UTF-8, no NUL characters (a binary file is refused naming the offset of the bad byte);
- YAML: the safe loader (no tags that build objects) with the document's nesting depth bounded
  (``max_depth``) and its *expanded* size bounded (``max_nodes`` values, counting every use of
  an anchor as a copy), which refuses a "billion laughs" file of nested aliases in microseconds;
- JSON: the same depth and size bounds on the decoded value.

Errors are :class:`UserFileError` (a ValueError) whose text is one line naming the file.
"""

from __future__ import annotations

import json
import os

import yaml
from yaml.composer import Composer
from yaml.nodes import MappingNode, SequenceNode

MAX_BYTES = 1 << 20  # [bytes] a parameter file or spec is a few kB; 1 MiB is generous
MAX_DEPTH = 64  # nesting levels of maps and lists
MAX_NODES = 100_000  # values in the document as its reader sees it (aliases expanded)


class UserFileError(ValueError):
    """A user file that cannot be used; ``str()`` is one line naming the file and the reason."""


def read_text(path, what: str = "file", max_bytes: int = MAX_BYTES) -> str:
    """The text of ``path`` (UTF-8), at most ``max_bytes``; UserFileError naming ``what`` and the
    file."""
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > max_bytes:
                raise UserFileError(
                    f"{what} {name}: {size} bytes; allowed at most {max_bytes} bytes"
                )
            data = f.read(
                max_bytes + 1
            )  # a file that grows while read (or a pipe) is still bounded
    except OSError as exc:
        raise UserFileError(f"{what} {name}: cannot be read ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise UserFileError(
            f"{what} {name}: more than {max_bytes} bytes; allowed at most {max_bytes} bytes"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserFileError(
            f"{what} {name}: not a text file (byte 0x{data[exc.start]:02x} at offset {exc.start} "
            f"is not UTF-8)"
        ) from None
    if "\x00" in text:
        raise UserFileError(
            f"{what} {name}: not a text file (a NUL character at offset {text.index(chr(0))})"
        )
    return text


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader whose composer refuses documents nested deeper than ``max_depth``."""

    max_depth = MAX_DEPTH

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > self.max_depth:
                mark = self.peek_event().start_mark
                raise UserFileError(
                    f"nested deeper than {self.max_depth} levels (line {mark.line + 1})"
                )
            return Composer.compose_node(self, parent, index)
        finally:
            self._depth -= 1


def _expanded_size(node, limit: int) -> int:
    """Values in the composed YAML ``node`` once every alias is expanded, stopping past
    ``limit``."""
    sizes: dict[int, int] = {}

    def size(n) -> int:
        key = id(n)
        if key in sizes:  # an anchored node used again: one more copy of all it holds
            return sizes[key]
        sizes[key] = limit + 1  # a node that contains itself (&a [*a]) expands without end
        total = 1
        if isinstance(n, SequenceNode):
            children = n.value
        elif isinstance(n, MappingNode):
            children = [item for pair in n.value for item in pair]
        else:
            children = ()
        for child in children:
            total += size(child)
            if total > limit:
                break
        sizes[key] = total
        return total

    return size(node)


def parse_yaml(text: str, where: str, max_depth: int = MAX_DEPTH, max_nodes: int = MAX_NODES):
    """The YAML ``text`` as Python values, bounded as the module doc says; UserFileError naming
    ``where``."""
    loader = type("Loader", (_BoundedLoader,), {"max_depth": max_depth})(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_size(node, max_nodes) > max_nodes:
            raise UserFileError(
                f"{where}: expands to more than {max_nodes} values (aliases of aliases: refused)"
            )
        return loader.construct_document(node)
    except UserFileError as exc:
        raise UserFileError(
            str(exc) if str(exc).startswith(where) else f"{where}: {exc}"
        ) from None
    except yaml.YAMLError as exc:
        text = " ".join(str(exc).split())
        raise UserFileError(f"{where} is not valid YAML: {text[:300]}") from None
    except (
        RecursionError,
        MemoryError,
        ValueError,
        TypeError,
    ) as exc:  # constructors on odd scalars
        raise UserFileError(
            f"{where} cannot be read as YAML: {type(exc).__name__}: {str(exc)[:200]}"
        ) from None
    finally:
        loader.dispose()


def _json_size(value, limit: int, depth: int, max_depth: int) -> int:
    if depth > max_depth:
        raise UserFileError(f"nested deeper than {max_depth} levels")
    if isinstance(value, dict):
        children = [*value.keys(), *value.values()]
    elif isinstance(value, list):
        children = value
    else:
        return 1
    total = 1
    for child in children:
        total += _json_size(child, limit, depth + 1, max_depth)
        if total > limit:
            break
    return total


def parse_json(text: str, where: str, max_depth: int = MAX_DEPTH, max_nodes: int = MAX_NODES):
    """The JSON ``text`` as Python values, bounded in depth and size; UserFileError naming
    ``where``."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise UserFileError(f"{where}: nested deeper than {max_depth} levels") from None
    except ValueError as exc:
        raise UserFileError(f"{where} is not valid JSON: {exc}") from None
    try:
        if _json_size(value, max_nodes, 1, max_depth) > max_nodes:
            raise UserFileError(f"more than {max_nodes} values")
    except UserFileError as exc:
        raise UserFileError(f"{where}: {exc}") from None
    return value


def load(
    path,
    what: str = "file",
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
):
    """The YAML (or, for a ``.json`` name, JSON) file ``path`` as Python values, every bound
    applied."""
    name = os.fspath(path)
    text = read_text(name, what, max_bytes)
    parse = parse_json if name.lower().endswith(".json") else parse_yaml
    return parse(text, f"{what} {name}", max_depth, max_nodes)
