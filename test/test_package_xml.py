"""package.xml lists every runtime dependency that afm_ros/ imports (rosdep keys)."""

import ast
import sys
from pathlib import Path
from xml.etree import ElementTree

ROOT = Path(__file__).resolve().parents[1]

# Python module -> rosdep key (rosdistro rosdep/python.yaml; python3-mcap-pip: see package.xml)
PYTHON_KEYS = {
    "numpy": "python3-numpy",
    "numba": "python3-numba",
    "scipy": "python3-scipy",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
    "mcap": "python3-mcap-pip",
    "yaml": "python3-yaml",
    "PIL": "python3-pil",
    "gwyfile": "python3-gwyfile-pip",
    "foxglove": "python3-foxglove-sdk-pip",
    "xarray": "python3-xarray",
    "zarr": "python3-zarr",
    "dask": "python3-dask",
    "distributed": "python3-distributed",
}


def imported_top_level_modules():
    found = {}
    for path in sorted((ROOT / "afm_ros").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in ("afm_ros", "__future__"):
                    found.setdefault(top, path.relative_to(ROOT).as_posix())
    return found


def test_every_imported_module_is_an_exec_depend():
    package = ElementTree.parse(ROOT / "package.xml").getroot()
    exec_depends = {
        e.text.strip() for tag in ("exec_depend", "depend") for e in package.findall(tag)
    }
    missing = {
        module: (PYTHON_KEYS.get(module, module), where)
        for module, where in imported_top_level_modules().items()
        if PYTHON_KEYS.get(module, module) not in exec_depends
    }
    assert not missing, (
        f"package.xml lacks exec_depend for (module: (rosdep key, first importer)) {missing}"
    )


def test_the_package_does_not_import_the_benchmarks():
    # benchmarks/ (repository root) is not installed: the package must not need it
    assert "benchmarks" not in imported_top_level_modules()


def test_the_scan_sees_the_known_imports():
    modules = imported_top_level_modules()
    assert {"rclpy", "numpy", "numba", "mcap", "tqdm", "std_msgs"} <= set(modules)


def test_the_launch_file_is_installed_and_describes_the_instrument():
    """launch/afm.launch.py, as ROS packages ship one: installed into share/afm_ros/launch
    (setup.py) and, where ROS 2's launch is importable (it is not on PyPI), it builds the four
    nodes and the recorder."""
    import pytest

    setup = (ROOT / "setup.py").read_text()
    assert '("share/" + package_name + "/launch", glob("launch/*.launch.py"))' in setup
    # (the repository's own launch/ folder is a namespace package of that name: ask for the real
    # one)
    try:
        from launch import LaunchDescription
    except ImportError:
        pytest.skip(
            "ROS 2's launch is not on PyPI: the launch file is checked where ROS is installed "
            "(ros2 launch afm_ros afm.launch.py)"
        )
    import importlib.util

    spec = importlib.util.spec_from_file_location("afm_launch", ROOT / "launch" / "afm.launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert isinstance(description, LaunchDescription)
    executables = {getattr(e, "node_executable", None) for e in description.entities}
    assert {
        "cantilever_node",
        "lockin_node",
        "z_controller_node",
        "scanner_node",
        "recorder_node",
    } <= executables


def test_the_launch_file_is_valid_python_naming_only_installed_executables():
    import ast

    tree = ast.parse((ROOT / "launch" / "afm.launch.py").read_text())
    names = {
        n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
    }
    setup = (ROOT / "setup.py").read_text()
    for node in ("cantilever", "lockin", "z_controller", "scanner"):
        assert node in names and f'"{node}_node = ' in setup
    assert "recorder_node" in names and '"recorder_node = ' in setup
