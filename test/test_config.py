"""config/afm.yaml and the parameter tables of docs/parameters.md agree with the parameter specs
(one source)."""

from pathlib import Path

import pytest
import yaml

from afm_ros.core.specs import node_key, node_specs, table_text, yaml_text

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def config():
    return yaml.safe_load((ROOT / "config" / "afm.yaml").read_text())


def test_every_node_has_specs():
    # every node (afm_ros/nodes/<name>_node.py) declares its parameters through specs
    nodes = {p.stem.removesuffix("_node") for p in (ROOT / "afm_ros" / "nodes").glob("*_node.py")}
    assert "bimodal" in nodes and "cantilever" in nodes
    assert set(node_specs()) == nodes


def test_yaml_file_is_the_generator_output():
    # regenerate with: python -m afm_ros.tools.config_gen yaml > config/afm.yaml
    assert (ROOT / "config" / "afm.yaml").read_text() == yaml_text()


def test_yaml_keys_match_every_namespace(config):
    # /**/<node>: rcl applies the section to the node under any namespace (-r __ns:=/afm1)
    assert set(config) == {node_key(node) for node in node_specs()}
    assert all(key.startswith("/**/") for key in config)


def test_yaml_holds_every_spec_default_and_validates(config):
    for node, specs in node_specs().items():
        params = config[node_key(node)]["ros__parameters"]
        assert set(params) == set(specs), f"{node}: YAML and specs list different parameters"
        for name, spec in specs.items():
            assert spec.validate(params[name]) == spec.default, f"{node}.{name}"


def test_parameter_tables_match_specs():
    doc = (ROOT / "docs" / "parameters.md").read_text()
    for row in table_text().splitlines()[2:]:
        assert row in doc, f"docs/parameters.md parameter table is missing or stale: {row}"


def test_running_nodes_describe_their_parameters_as_the_specs(
    ros_context, ros_executor, ros_namespace, tmp_path
):
    """What `ros2 param describe` shows (the describe_parameters service) comes from the same
    specs: description with unit and allowed range, read-only flag, and the default value."""
    import rclpy
    from rclpy.parameter import Parameter, parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    from afm_ros.nodes.cantilever_node import CantileverNode
    from afm_ros.nodes.lockin_node import LockInNode
    from afm_ros.nodes.recorder_node import RecorderNode
    from afm_ros.nodes.scanner_node import ScannerNode
    from afm_ros.nodes.z_controller_node import ZControllerNode

    kw = {"context": ros_context, "namespace": ros_namespace}
    nodes = {
        "cantilever": CantileverNode(**kw),
        "lockin": LockInNode(**kw),
        "z_controller": ZControllerNode(**kw),
        "scanner": ScannerNode(**kw),
        "recorder": RecorderNode(
            parameter_overrides=[Parameter("output", value=str(tmp_path / "s.mcap"))], **kw
        ),
    }
    client_node = rclpy.create_node("describer", context=ros_context, namespace=ros_namespace)
    for node in [*nodes.values(), client_node]:
        ros_executor.add_node(node)
    specs_by_node = node_specs()
    for name, node in nodes.items():
        specs = specs_by_node[name]
        client = AsyncParameterClient(client_node, f"{ros_namespace}/{name}")
        assert client.wait_for_services(timeout_sec=10.0)
        future = client.describe_parameters(list(specs))
        ros_executor.spin_until_future_complete(future, timeout_sec=10.0)
        descriptors = future.result().descriptors
        values_future = client.get_parameters(list(specs))
        ros_executor.spin_until_future_complete(values_future, timeout_sec=10.0)
        values = values_future.result().values
        for (pname, spec), descriptor, value in zip(specs.items(), descriptors, values):
            assert descriptor.name == pname
            assert spec.range_text() in descriptor.description, (
                name,
                pname,
                descriptor.description,
            )
            if spec.unit:
                assert f"[{spec.unit}]" in descriptor.description, (
                    name,
                    pname,
                    descriptor.description,
                )
            assert descriptor.read_only == (not spec.live), (name, pname)
            if name == "recorder" and pname == "output":
                continue  # overridden above so that the test writes into its temp dir
            actual = parameter_value_to_python(value)
            assert actual == spec.default, (name, pname, actual, spec.default)


def test_shipped_file_applies_under_a_namespace(ros_context, ros_namespace, tmp_path):
    """The /**/<node> keys match the node in any namespace (here the test's /t_... namespace): a
    temp copy of config/afm.yaml with one changed value gives the node that value (and the
    unchanged file gives the defaults)."""
    from afm_ros.nodes.z_controller_node import ZControllerNode

    shipped = (ROOT / "config" / "afm.yaml").read_text()
    assert "\n    setpoint: 4.8e-08\n" in shipped and "\n    p_gain: 0.1\n" in shipped
    modified = tmp_path / "afm.yaml"
    modified.write_text(
        shipped.replace("\n    setpoint: 4.8e-08\n", "\n    setpoint: 3.5e-08\n").replace(
            "\n    p_gain: 0.1\n", "\n    p_gain: 1\n"
        )
    )  # an integer for a double
    for path, setpoint, p_gain in [
        (ROOT / "config" / "afm.yaml", 4.8e-08, 0.1),
        (modified, 3.5e-08, 1.0),
    ]:
        node = ZControllerNode(
            context=ros_context,
            namespace=ros_namespace,
            cli_args=["--ros-args", "--params-file", str(path)],
        )
        try:
            assert node.get_fully_qualified_name() == f"{ros_namespace}/z_controller"
            assert node.get_parameter("setpoint").value == setpoint
            assert node.get_parameter("p_gain").value == p_gain
            assert type(node.get_parameter("p_gain").value) is float
        finally:
            node.destroy_node()
