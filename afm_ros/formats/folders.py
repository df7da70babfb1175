"""Output folders checked before a long job starts (no ROS), not after it when the result is lost.

:func:`check_output_directory` is the one rule for the scanner node's ``output_directory`` (when
the parameter is set, and again when a scan starts) and for ``afm_instrument --image`` before it
engages:

- ``''`` is the working directory; ``~`` is expanded; a relative path is taken from the working
  directory of the process that writes;
- an existing path must be a folder (not a regular file) in which a file can be created (tried
  with a temporary file: permissions, read-only mounts and ACLs all show, also for root);
- a missing folder is created only as the last level of the path, under an existing writable
  folder that is not the file-system root: a chain of missing folders (``/data/afm/run1`` when
  ``/data`` is missing) or a folder directly under ``/`` is refused, so a typo never spreads
  folders over the disk;
- with ``need_bytes``, the file system must have that much free space.

Every refusal is a ValueError naming the field, the value and what is needed.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


def _size(n: float) -> str:
    for unit, factor in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= factor:
            return f"{n / factor:.1f} {unit}"
    return f"{int(n)} bytes"


def _probe(folder: Path, field: str, text: str) -> None:
    """ValueError unless a file can be created in ``folder``."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(
            f"{field}={text!r}: cannot write in {folder} ({exc.strerror}); allowed: a folder "
            f"this process can write to"
        ) from None


def check_output_directory(
    path,
    need_bytes: int = 0,
    create: bool = False,
    probe_write: bool = True,
    field: str = "output_directory",
) -> Path:
    """Check (and with ``create`` make) the output folder ``path`` by the rule of the module doc;
    return its absolute path. ``probe_write=False`` checks only what is cheap and cannot change by
    itself (a parameter being set): not a file, its parent exists. ValueError naming ``field``."""
    text = os.fspath(path) if path is not None else ""
    if not isinstance(text, str) or "\0" in text:
        raise ValueError(
            f"{field}={text!r} is not a usable path; allowed: a folder path ('' = the working "
            "directory)"
        )
    folder = Path(os.path.abspath(os.path.expanduser(text or ".")))
    if folder.exists():
        if not folder.is_dir():
            raise ValueError(
                f"{field}={text!r} is a file, not a folder; allowed: an existing folder, or a new "
                f"folder under an existing one"
            )
    else:
        parent = folder.parent
        if not parent.is_dir():
            raise ValueError(
                f"{field}={text!r}: {parent} does not exist; only the last level of a folder is "
                f"created: create {parent} first, or choose an existing folder"
            )
        if parent == Path(parent.anchor):
            raise ValueError(
                f"{field}={text!r} would be a new folder at the file-system root; create it "
                "yourself, "
                f"or choose a folder under an existing one"
            )
        if not (create and probe_write):
            if probe_write:
                _probe(parent, field, text)
            return folder
        try:
            folder.mkdir()
        except FileExistsError:
            if not folder.is_dir():
                raise ValueError(f"{field}={text!r} is a file, not a folder") from None
        except OSError as exc:
            raise ValueError(
                f"{field}={text!r}: cannot create {folder} ({exc.strerror})"
            ) from None
    if probe_write:
        _probe(folder, field, text)
        if need_bytes > 0:
            free = shutil.disk_usage(folder).free
            if free < need_bytes:
                raise ValueError(
                    f"{field}={text!r}: {_size(free)} free on its file system, a frame needs "
                    "about "
                    f"{_size(need_bytes)}; free some space or choose another folder"
                )
    return folder
