"""What ``afm_instrument`` reads from its ``--ros-args`` and where a run puts its files.

:class:`RosArgs` finds the parameter values the user gave (``-p name:=value``,
``-p node:name:=value``, ``--params-file``), the namespace (``-r __ns:=``) and ``--log-level``,
so the job does not override what the user chose. rcl applies ``-p node:name:=value`` only to a
node in the root namespace (its rule names the node without a namespace and rcl rejects
``/ns/node:``); under ``-r __ns:=/afm1`` the job passes those values to its nodes itself, so
``-p recorder:output:=F`` means the same in every namespace.

:func:`make_run_folder` creates the run's folder: ``afm_runs/<date>_<time>[_<namespace>]`` in the
working directory by default, never one that exists (two instruments started in the same second
get ``..._2``), so a run leaves one folder, not a dozen files in the working directory.
"""

from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass, field
from pathlib import Path

from afm_ros.formats import user_files
from afm_ros.formats.params_file import ParamsFileError, parameters_for

RUNS_DIR = "afm_runs"
_MISSING = object()


def _parse_value(text: str):
    """A ``-p`` value as rcl reads it (YAML)."""
    try:
        return user_files.parse_yaml(text, "a -p value")
    except user_files.UserFileError:
        return text


@dataclass
class RosArgs:
    """The parts of the ROS arguments the job needs (see the module doc)."""

    namespace: str = ""  # '' = root
    params: dict = field(default_factory=dict)  # node ('' = every node) -> {name: value} from -p
    files: list = field(default_factory=list)  # --params-file paths
    log_level: str | None = None

    @classmethod
    def parse(cls, argv: list[str]) -> "RosArgs":
        out = cls()
        inside = False
        i = 0
        while i < len(argv):
            arg = argv[i]
            if arg == "--ros-args":
                inside = True
            elif arg == "--":
                inside = False
            elif inside and i + 1 < len(argv):
                value = argv[i + 1]
                if arg in ("-p", "--param") and ":=" in value:
                    key, text = value.split(":=", 1)
                    node, _, name = key.rpartition(":")
                    out.params.setdefault(node, {})[name] = _parse_value(text)
                    i += 1
                elif arg == "--params-file":
                    out.files.append(value)
                    i += 1
                elif arg in ("-r", "--remap"):
                    if value.startswith("__ns:="):
                        out.namespace = "/" + value.split(":=", 1)[1].strip("/")
                        out.namespace = "" if out.namespace == "/" else out.namespace
                    i += 1
                elif arg == "--log-level":
                    out.log_level = value
                    i += 1
            i += 1
        return out

    def _file_values(self, node: str) -> dict:
        """What the params files give ``node`` of this namespace, matched as rcl matches node keys
        (wildcards first, the node's own key last; a later file wins)."""

        values: dict = {}
        for path in self.files:
            try:
                values.update(parameters_for(path, f"{self.namespace}/{node}"))
            except ParamsFileError:
                # no entry for the node; a file rcl cannot read it reports itself, before the job
                continue
        return values

    def value(self, node: str, name: str, default=None):
        """The value the user gave ``node``'s parameter ``name`` (by -p, with or without the node,
        or a params file; -p wins over the files as in rcl), else ``default``."""
        for source in (
            self.params.get(node, {}),
            self.params.get("", {}),
            self._file_values(node),
        ):
            if name in source:
                return source[name]
        return default

    def given(self, node: str, name: str) -> bool:
        """True if the user set ``node``'s parameter ``name`` (see :meth:`value`)."""
        return self.value(node, name, _MISSING) is not _MISSING

    def node_rules(self, node: str) -> dict:
        """The ``-p node:name:=value`` values rcl does not apply to ``node`` because of the
        namespace."""
        return dict(self.params.get(node, {})) if self.namespace else {}


def make_run_folder(
    out: str | os.PathLike | None, namespace: str = "", now: _dt.datetime | None = None
) -> Path:
    """The run's folder: ``out`` as given (created if missing), or a new
    ``afm_runs/<date>_<time>[_<ns>]``.

    OSError (with the path) if it cannot be created."""
    if out is not None:
        path = Path(out)
        path.mkdir(parents=True, exist_ok=True)
        if not path.is_dir():
            raise NotADirectoryError(f"{path} is not a folder")
        return path
    stamp = (now or _dt.datetime.now()).strftime("%Y-%m-%d_%H-%M-%S")
    suffix = "_" + namespace.strip("/").replace("/", "_") if namespace.strip("/") else ""
    base = Path(RUNS_DIR)
    base.mkdir(exist_ok=True)
    for n in range(1, 1000):
        path = base / (f"{stamp}{suffix}" + (f"_{n}" if n > 1 else ""))
        try:
            path.mkdir()  # exclusive: never a folder another run uses
            return path
        except FileExistsError:
            continue
    raise FileExistsError(f"no free run folder name under {base} for {stamp}{suffix}")
