"""The package's layers hold (README, "Layout"): each layer imports only those below it.

    afm_ros (root helpers) <- formats <- core <- nodes <- client <- tools;  benchmarks on top

Read from the source with ``ast`` (every import, also inside functions; type-checking-only
imports left out): no import from a lower layer to a higher one, no import circle between modules,
no private name (a leading underscore) imported from another module, nothing of the package imports
the benchmarks, and the in-process client loads no rclpy.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {
    "afm_ros": 0,
    "afm_ros.formats": 1,
    "afm_ros.core": 2,
    "afm_ros.nodes": 3,
    "afm_ros.client": 4,
    "afm_ros.tools": 5,
    "benchmarks": 6,
}


def _modules() -> dict[str, Path]:
    out = {}
    for folder in ("afm_ros", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


MODULES = _modules()


def layer(module: str) -> int:
    """The layer of a module: its longest prefix in LAYERS."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        if prefix in LAYERS:
            return LAYERS[prefix]
    raise KeyError(module)


def _type_checking_only(node, parents) -> bool:
    p = parents.get(node)
    while p is not None:
        if isinstance(p, ast.If) and "TYPE_CHECKING" in ast.unparse(p.test):
            return True
        p = parents.get(p)
    return False


def imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(module imported, names imported from it, line) of every import of the package or the
    benchmarks."""
    tree = ast.parse(path.read_text())
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    out = []
    for node in ast.walk(tree):
        if _type_checking_only(node, parents):
            continue
        if (
            isinstance(node, ast.ImportFrom)
            and node.module
            and node.module.split(".")[0] in ("afm_ros", "benchmarks")
        ):
            names = [a.name for a in node.names]
            submodules = [f"{node.module}.{n}" for n in names if f"{node.module}.{n}" in MODULES]
            out += [(m, [], node.lineno) for m in submodules]
            out.append(
                (
                    node.module,
                    [n for n in names if f"{node.module}.{n}" not in MODULES],
                    node.lineno,
                )
            )
        elif isinstance(node, ast.Import):
            out += [
                (a.name, [], node.lineno)
                for a in node.names
                if a.name.split(".")[0] in ("afm_ros", "benchmarks")
            ]
    return out


@pytest.mark.slow
def test_no_layer_imports_a_higher_one():
    wrong = [
        f"{name} (layer {layer(name)}) imports {target} (layer {layer(target)}) at line {line}"
        for name, path in MODULES.items()
        for target, _, line in imports(path)
        if layer(target) > layer(name)
    ]
    assert not wrong, "\n".join(wrong)


@pytest.mark.slow
def test_no_import_circle():
    graph = {
        name: {t for t, _, _ in imports(path) if t in MODULES and t != name}
        for name, path in MODULES.items()
    }
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, circles


@pytest.mark.slow
def test_no_private_name_is_imported_from_another_module():
    wrong = [
        f"{name}:{line} imports {n} from {target}"
        for name, path in MODULES.items()
        for target, names, line in imports(path)
        for n in names
        if n.startswith("_") and target != name
    ]
    assert not wrong, "\n".join(wrong)


@pytest.mark.slow
def test_nothing_in_the_package_imports_the_benchmarks():
    wrong = [
        f"{name} imports {t}"
        for name, path in MODULES.items()
        if layer(name) < LAYERS["benchmarks"]
        for t, _, _ in imports(path)
        if t.split(".")[0] == "benchmarks"
    ]
    assert not wrong, wrong


ROS = (
    "rclpy",
    "rosidl",
    "rcl_interfaces",
    "std_msgs",
    "std_srvs",
    "sensor_msgs",
    "diagnostic_msgs",
    "builtin_interfaces",
    "rosgraph_msgs",
    "geometry_msgs",
    "ament_index_python",
)


def test_formats_and_core_import_no_ros_at_module_level():
    """formats/ and core/ are numpy + numba: a ROS library only inside the function that needs
    it."""
    wrong = []
    for name, path in MODULES.items():
        if layer(name) not in (
            LAYERS["afm_ros.formats"],
            LAYERS["afm_ros.core"],
            LAYERS["afm_ros"],
        ):
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = (
                    [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else [node.module or ""]
                )
                wrong += [
                    f"{name}:{node.lineno} imports {m}" for m in mods if m.split(".")[0] in ROS
                ]
    assert not wrong, wrong


CORES = [
    name for name in MODULES if layer(name) in (LAYERS["afm_ros.formats"], LAYERS["afm_ros.core"])
]


@pytest.mark.parametrize(
    "code",
    [
        "from afm_ros.client import Microscope, NotEngaged, ClientError",
        "import " + ", ".join(CORES),
    ],
)
def test_the_in_process_client_and_the_cores_load_no_rclpy(code):
    result = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint('rclpy' in sys.modules)"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert result.returncode == 0 and result.stdout.strip() == "False", result.stderr


def test_no_nodes_private_member_is_used_outside_its_file():
    """A node's private attributes and methods (a leading underscore) are its own: tools, the
    client, benchmarks, examples and tests use its public surface."""
    private = set()
    for path in (ROOT / "afm_ros" / "nodes").glob("*.py"):
        for cls in (
            n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ClassDef)
        ):
            for node in ast.walk(cls):
                if (
                    isinstance(node, ast.FunctionDef)
                    and node.name.startswith("_")
                    and not node.name.startswith("__")
                ):
                    private.add(node.name)
                if (
                    isinstance(node, ast.Attribute)
                    and isinstance(node.value, ast.Name)
                    and node.value.id == "self"
                    and node.attr.startswith("_")
                    and not node.attr.startswith("__")
                ):
                    private.add(node.attr)
    wrong = []
    for folder in ("afm_ros/tools", "afm_ros/client", "benchmarks", "examples", "test"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if (
                    isinstance(node, ast.Attribute)
                    and node.attr in private
                    and not (isinstance(node.value, ast.Name) and node.value.id == "self")
                ):
                    wrong.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert not wrong, "\n".join(wrong)
