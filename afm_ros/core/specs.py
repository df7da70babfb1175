"""Every node's parameter specs in one registry, and what is generated from them (no ROS).

``config/afm.yaml``, the parameter tables of docs/parameters.md and each node's ``--help`` are made
from :data:`NODE_SPECS`; ``python -m afm_ros.tools.config_gen yaml|table`` prints them and a test
checks that the committed files agree.
"""

from __future__ import annotations

from afm_ros.core.approach import Z_NODE_SPECS
from afm_ros.core.bimodal_scan import BIMODAL_NODE_SPECS, BIMODAL_SPECS
from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS
from afm_ros.core.fm import FM_SPECS
from afm_ros.core.live_view import LIVE_VIEW_SPECS
from afm_ros.core.recording import RECORDER_SPECS, REPLAY_SPECS
from afm_ros.core.scanner import SCANNER_NODE_SPECS
from afm_ros.core.tune import LOCKIN_NODE_SPECS
from afm_ros.formats.params_file import yaml_value

# node name -> its parameter specs (name -> ParamSpec), in the order of the docs
NODE_SPECS = {
    "cantilever": CANTILEVER_NODE_SPECS,
    "lockin": LOCKIN_NODE_SPECS,
    "z_controller": Z_NODE_SPECS,
    "pll": FM_SPECS,
    "recorder": RECORDER_SPECS,
    "replay": REPLAY_SPECS,
    "scanner": SCANNER_NODE_SPECS,
    "live_view": LIVE_VIEW_SPECS,
    "bimodal": {**BIMODAL_SPECS, **BIMODAL_NODE_SPECS},
}


def node_specs() -> dict:
    """Spec dicts of every node, by node name."""
    return dict(NODE_SPECS)


def node_key(node: str) -> str:
    """The params-file key of a node: ``/**/<node>`` matches the node in every namespace (rcl's
    YAML parser supports ``/**`` and ``/*`` wildcards in node names)."""
    return f"/**/{node}"


def yaml_text(nodes: dict | None = None) -> str:
    nodes = node_specs() if nodes is None else nodes
    lines = [
        "# Defaults of every afm_ros node: the seed notebook's cantilever and DMT sample.",
        "# Generated from the parameter specs by `python -m afm_ros.tools.config_gen yaml`; SI "
        "units.",
        "# Use with: ros2 run afm_ros <node> --ros-args --params-file config/afm.yaml",
        "# The keys are /**/<node name>, so the file applies under any namespace (-r "
        "__ns:=/afm1).",
    ]
    for node, specs in nodes.items():
        lines += [f"{node_key(node)}:", "  ros__parameters:"]
        for name, spec in specs.items():
            unit = f" [{spec.unit}]" if spec.unit else ""
            lines.append(f"    # {spec.description}{unit}; allowed {spec.range_text()}")
            lines.append(f"    {name}: {yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"


def spec_cells(spec) -> tuple[str, str, str, str]:
    """(default, unit, range, live) of a spec as the parameter tables show them (README,
    ``--help``)."""
    default = (
        yaml_value(spec.default) if not isinstance(spec.default, str) else f"`{spec.default}`"
    )
    return default, spec.unit or "-", spec.range_text(), "yes" if spec.live else "no"


def table_text(nodes: dict | None = None) -> str:
    nodes = node_specs() if nodes is None else nodes
    rows = [
        "| node | name | default | unit | range | live | description |",
        "|---|---|---|---|---|---|---|",
    ]
    for node, specs in nodes.items():
        for name, spec in specs.items():
            default, unit, allowed, live = spec_cells(spec)
            rows.append(
                f"| {node} | `{name}` | {default} | {unit} | {allowed} | {live} | "
                f"{spec.description} |"
            )
    return "\n".join(rows) + "\n"


def session_table(specs: dict) -> str:
    """The Markdown table of a command's parameters (name, default, unit, range, description)."""
    rows = ["| name | default | unit | range | description |", "|---|---|---|---|---|"]
    for name, spec in specs.items():
        default, unit, allowed, _ = spec_cells(spec)
        rows.append(f"| `{name}` | {default} | {unit} | {allowed} | {spec.description} |")
    return "\n".join(rows) + "\n"
