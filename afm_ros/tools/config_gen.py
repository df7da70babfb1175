"""Generate ``config/afm.yaml`` and the README parameter tables from the parameter specs.

``python -m afm_ros.tools.config_gen yaml`` prints the YAML; ``python -m afm_ros.tools.config_gen table``
prints the Markdown parameter table. A test checks that the committed files agree with the specs.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# node name -> (module, specs attribute)
NODE_SPECS = {
    "cantilever": ("afm_ros.core.cantilever_params", "CANTILEVER_NODE_SPECS"),
    "lockin": ("afm_ros.core.tune", "LOCKIN_NODE_SPECS"),
    "z_controller": ("afm_ros.core.approach", "Z_NODE_SPECS"),
    "pll": ("afm_ros.core.fm", "FM_SPECS"),
    "recorder": ("afm_ros.formats.mcap_io", "RECORDER_SPECS"),
    "replay": ("afm_ros.formats.mcap_io", "REPLAY_SPECS"),
    "scanner": ("afm_ros.core.scanner", "SCANNER_NODE_SPECS"),
    "live_view": ("afm_ros.core.live_view", "LIVE_VIEW_SPECS"),
}


def node_specs() -> dict:
    """Spec dicts of every node whose module is present, by node name."""
    out = {}
    for node, (module, attr) in NODE_SPECS.items():
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError:
            continue
        specs = getattr(mod, attr, None)
        if specs is not None:
            out[node] = specs
    return out


def yaml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        # shortest round-trip text, always with a '.' and a signed exponent so that YAML 1.1
        # readers (PyYAML) and rcl's parser both read a double
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


def node_key(node: str) -> str:
    """The params-file key of a node: ``/**/<node>`` matches the node in every namespace (rcl's
    YAML parser supports ``/**`` and ``/*`` wildcards in node names)."""
    return f"/**/{node}"


def yaml_text(nodes: dict | None = None) -> str:
    nodes = node_specs() if nodes is None else nodes
    lines = ["# Defaults of every afm_ros node: the seed notebook's cantilever and DMT sample.",
             "# Generated from the parameter specs by `python -m afm_ros.tools.config_gen yaml`; SI units.",
             "# Use with: ros2 run afm_ros <node> --ros-args --params-file config/afm.yaml",
             "# The keys are /**/<node name>, so the file applies under any namespace (-r __ns:=/afm1)."]
    for node, specs in nodes.items():
        lines += [f"{node_key(node)}:", "  ros__parameters:"]
        for name, spec in specs.items():
            unit = f" [{spec.unit}]" if spec.unit else ""
            lines.append(f"    # {spec.description}{unit}; allowed {spec.range_text()}")
            lines.append(f"    {name}: {yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"


def spec_cells(spec) -> tuple[str, str, str, str]:
    """(default, unit, range, live) of a spec as the parameter tables show them (README, ``--help``)."""
    default = yaml_value(spec.default) if not isinstance(spec.default, str) else f"`{spec.default}`"
    return default, spec.unit or "-", spec.range_text(), "yes" if spec.live else "no"


def table_text(nodes: dict | None = None) -> str:
    nodes = node_specs() if nodes is None else nodes
    rows = ["| node | name | default | unit | range | live | description |",
            "|---|---|---|---|---|---|---|"]
    for node, specs in nodes.items():
        for name, spec in specs.items():
            default, unit, allowed, live = spec_cells(spec)
            rows.append(f"| {node} | `{name}` | {default} | {unit} | {allowed} | {live} | {spec.description} |")
    return "\n".join(rows) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.tools.config_gen", description=__doc__)
    parser.add_argument("what", choices=["yaml", "table"])
    args = parser.parse_args(argv)
    sys.stdout.write(yaml_text() if args.what == "yaml" else table_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
