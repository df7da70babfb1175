"""Parameters as ROS users type them (issue 7): real nodes, the real parameter services.

Values are produced exactly as ros2cli (Jazzy, ros2cli 0.32) produces them: ``ros2 param set``
turns its text into a ParameterValue with ``rclpy.parameter.get_parameter_value`` (YAML 1.1:
``30e-9`` is a string, ``30`` an integer); ``ros2 param dump`` / ``load`` are replicated below
from the ros2cli source (copied functions name their file and branch). Every call goes through
the node's services from a second node; futures are waited on with generous timeouts.
"""

from __future__ import annotations

import re
import sys

import pytest
import yaml
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType

from afm_ros.core.specs import node_specs

pytestmark = pytest.mark.ros

TIMEOUT = 30.0
TYPE_OF_KIND = {
    float: ParameterType.PARAMETER_DOUBLE,
    int: ParameterType.PARAMETER_INTEGER,
    bool: ParameterType.PARAMETER_BOOL,
    str: ParameterType.PARAMETER_STRING,
}


# --- ros2cli, copied ------------------------------------------------------------------------
# ros2cli, branch jazzy (0.32.2), ros2param/ros2param/api/__init__.py: get_value
def get_value(*, parameter_value):
    """Get the value from a ParameterValue."""
    from rclpy.parameter import parameter_value_to_python

    value = None
    try:
        value = parameter_value_to_python(parameter_value)
    except RuntimeError as e:
        print(f"Runtime error {e} raised")
    return value


# ros2cli, branch jazzy (0.32.2), ros2param/ros2param/verb/dump.py: DumpVerb.insert_dict
def insert_dict(dictionary, key, value):
    from rclpy.parameter import PARAMETER_SEPARATOR_STRING

    split = key.split(PARAMETER_SEPARATOR_STRING, 1)
    if len(split) > 1:
        if split[0] not in dictionary:
            dictionary[split[0]] = {}
        insert_dict(dictionary[split[0]], split[1], value)
    else:
        dictionary[key] = value


class Ros2Param:
    """``ros2 param set/get/describe/dump/load`` over the parameter services, as ros2cli does them.

    set: ros2param/verb/set.py (jazzy) builds ``Parameter(name,
    get_parameter_value(string_value=text))`` and calls set_parameters. load:
    ros2param/api/__init__.py (jazzy) load_parameter_file calls
    ``AsyncParameterClient.load_parameter_file(file, use_wildcard)`` (rclpy:
    ``parameter_dict_from_yaml_file``, which re-parses ``str(value)`` with get_parameter_value,
    then set_parameters), used here as is.
    """

    def __init__(self, executor, node):
        self.executor = executor
        self.node = node
        self._clients = {}

    def client(self, node_name):
        from rclpy.parameter_client import AsyncParameterClient

        if node_name not in self._clients:
            client = AsyncParameterClient(self.node, node_name)
            assert client.wait_for_services(timeout_sec=TIMEOUT), (
                f"no parameter services for {node_name}"
            )
            self._clients[node_name] = client
        return self._clients[node_name]

    def wait(self, future):
        self.executor.spin_until_future_complete(future, timeout_sec=TIMEOUT)
        assert future.done(), "no answer from the parameter service within the timeout"
        return future.result()

    def set(self, node_name, name, text):
        from rclpy.parameter import get_parameter_value

        msg = ParameterMsg(name=name, value=get_parameter_value(string_value=text))
        results = self.wait(self.client(node_name).set_parameters([msg])).results
        assert len(results) == 1
        return results[0]

    def delete(self, node_name, name):
        # ros2cli, branch jazzy (0.32.2), ros2param/api/__init__.py: call_delete_parameters uses
        # AsyncParameterClient.delete_parameters (a NOT_SET value through set_parameters)
        results = self.wait(self.client(node_name).delete_parameters([name])).results
        assert len(results) == 1
        return results[0]

    def get(self, node_name, name):
        value = self.wait(self.client(node_name).get_parameters([name])).values[0]
        return value.type, get_value(parameter_value=value)

    def describe(self, node_name, names):
        return self.wait(self.client(node_name).describe_parameters(list(names))).descriptors

    def dump(self, node_name):
        # ros2cli, branch jazzy (0.32.2), ros2param/ros2param/verb/dump.py: DumpVerb.main
        client = self.client(node_name)
        parameter_names = sorted(self.wait(client.list_parameters()).result.names)
        response = self.wait(client.get_parameters(parameter_names))
        parameter_values = [get_value(parameter_value=i) for i in response.values]
        yaml_output = {node_name: {"ros__parameters": {}}}
        for param_name, pval in zip(parameter_names, parameter_values):
            insert_dict(yaml_output[node_name]["ros__parameters"], param_name, pval)
        return yaml.dump(yaml_output, default_flow_style=False)

    def load(self, node_name, path):
        from rclpy.parameter import parameter_dict_from_yaml_file

        future = self.client(node_name).load_parameter_file(str(path), True)
        parameters = list(parameter_dict_from_yaml_file(str(path), True).values())
        results = self.wait(future).results
        assert len(results) == len(parameters), "Not all parameters set"
        return [(p.name, r) for p, r in zip(parameters, results)]


# --- fixtures ----------------------------------------------------------------------------
def _replay_file(path):
    """A tiny session (one Float64 message) so that a replay node can be constructed."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64

    from afm_ros.formats.mcap_io import SessionWriter

    writer = SessionWriter(path)
    channel = writer.add_channel("/x", "std_msgs/msg/Float64")
    writer.write(channel, serialize_message(Float64(data=1.0)), 1_000_000_000)
    writer.close()
    return path


@pytest.fixture
def afm_nodes(ros_context, ros_executor, ros_namespace, tmp_path):
    """All five afm_ros nodes in one namespace, and a ros2param stand-in on a second node.
    The cantilever runs at real_time_factor 0.01 (keeps the CPU free); the replay waits 60 s
    before it would publish anything."""
    import rclpy
    from rclpy.parameter import Parameter

    from afm_ros.nodes.cantilever_node import CantileverNode
    from afm_ros.nodes.lockin_node import LockInNode
    from afm_ros.nodes.recorder_node import RecorderNode
    from afm_ros.nodes.replay_node import ReplayNode
    from afm_ros.nodes.scanner_node import ScannerNode
    from afm_ros.nodes.z_controller_node import ZControllerNode

    kw = {"context": ros_context, "namespace": ros_namespace}
    nodes = {
        "cantilever": CantileverNode(
            parameter_overrides=[Parameter("real_time_factor", value=0.01)], **kw
        ),
        "lockin": LockInNode(**kw),
        "z_controller": ZControllerNode(**kw),
        "recorder": RecorderNode(
            parameter_overrides=[
                Parameter("output", value=str(tmp_path / "s.mcap")),
                Parameter("topics", value="/no_such_topic"),
            ],
            **kw,
        ),
        "replay": ReplayNode(
            parameter_overrides=[
                Parameter("file", value=str(_replay_file(tmp_path / "r.mcap"))),
                Parameter("start_delay", value=60.0),
                Parameter("topic_prefix", value="replayed"),
            ],
            **kw,
        ),
        "scanner": ScannerNode(**kw),
    }
    cli_node = rclpy.create_node("ros2param_cli", context=ros_context, namespace=ros_namespace)
    for node in [*nodes.values(), cli_node]:
        ros_executor.add_node(node)
    return {f"{ros_namespace}/{name}": node for name, node in nodes.items()}, Ros2Param(
        ros_executor, cli_node
    )


def _full(nodes, short):
    return next(name for name in nodes if name.endswith("/" + short))


# --- tests -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "short,name,text,expected",
    [
        ("cantilever", "z_base", "30e-9", 30e-9),  # the README's command; YAML 1.1: a string
        ("z_controller", "setpoint", "40e-9", 40e-9),  # the README's command
        ("cantilever", "quality_factor", "30", 30.0),  # YAML integer for a double
        (
            "cantilever",
            "free_amplitude",
            "6e-08",
            6e-8,
        ),  # how ros2 param load re-reads a dumped 6e-08
        ("cantilever", "spring_constant", "1E1", 10.0),
        ("lockin", "time_constant", "3.0e-5", 3e-5),  # a YAML 1.1 float stays as it is
        ("z_controller", "z_min", "-1.5e-7", -1.5e-7),
        (
            "cantilever",
            "steps_per_period",
            "2.4e2",
            240,
        ),  # integer parameter: integral numeric string
        ("cantilever", "steps_per_period", "300.0", 300),  # integer parameter: integral double
        ("z_controller", "enabled", "'off'", False),  # a quoted YAML bool word arrives as a string
        ("cantilever", "publish_clock", "false", False),
        ("cantilever", "force_model", "none", "none"),
    ],
)
def test_values_typed_as_on_the_command_line_are_accepted_and_keep_the_declared_type(
    afm_nodes, short, name, text, expected
):
    nodes, cli = afm_nodes
    node = _full(nodes, short)
    spec = node_specs()[short][name]
    before = cli.describe(node, [name])[0]
    result = cli.set(node, name, text)
    assert result.successful, (node, name, text, result.reason)
    value_type, value = cli.get(node, name)
    assert value_type == TYPE_OF_KIND[spec.kind], (name, value_type)
    assert value == expected and type(value) is spec.kind, (name, value)
    after = cli.describe(node, [name])[0]
    assert after.type == before.type == TYPE_OF_KIND[spec.kind]


@pytest.mark.parametrize(
    "short,name,text",
    [
        ("cantilever", "z_base", "abc"),
        ("cantilever", "z_base", "30e-9m"),
        ("cantilever", "z_base", "true"),  # a bool is not a number
        ("cantilever", "z_base", "[1.0, 2.0]"),  # an array neither
        ("cantilever", "quality_factor", "0.2"),  # the README's refused example
        ("cantilever", "quality_factor", "0.5"),  # the open bound itself
        ("cantilever", "free_amplitude", "-1"),  # below the range, given as an integer
        ("cantilever", "z_base", "1e-3"),  # above the range, as a string
        ("cantilever", "steps_per_period", "2.55e1"),  # 25.5: not an integer
        ("cantilever", "steps_per_period", "10"),  # below the range
        ("cantilever", "publish_clock", "maybe"),
        ("cantilever", "force_model", "lj"),
        ("z_controller", "setpoint", "-1e-9"),
        ("lockin", "harmonic", "nine"),
        ("scanner", "pixels_per_line", "1"),
        ("scanner", "slow_scan_direction", "sideways"),
    ],
)
def test_refused_values_name_field_and_range_and_change_nothing(afm_nodes, short, name, text):
    nodes, cli = afm_nodes
    node = _full(nodes, short)
    spec = node_specs()[short][name]
    type_before, value_before = cli.get(node, name)
    descriptor_before = cli.describe(node, [name])[0]
    result = cli.set(node, name, text)
    assert not result.successful
    assert result.reason.startswith(f"{name}="), result.reason  # the spec's reason, not rclpy's
    assert spec.range_text() in result.reason, result.reason
    assert "Wrong parameter type" not in result.reason
    assert cli.get(node, name) == (type_before, value_before)
    descriptor_after = cli.describe(node, [name])[0]
    assert descriptor_after.type == descriptor_before.type == TYPE_OF_KIND[spec.kind]


@pytest.mark.parametrize(
    "short,name,best",
    [
        ("z_controller", "setpont", "setpoint"),  # the typo
        ("cantilever", "quality_factr", "quality_factor"),
        ("scanner", "pixel_per_line", "pixels_per_line"),
        ("lockin", "zzz", None),  # nothing close: every name is listed
    ],
)
def test_an_unknown_name_is_refused_naming_it_the_node_and_the_close_matches(
    afm_nodes, short, name, best
):
    nodes, cli = afm_nodes
    node = _full(nodes, short)
    specs = node_specs()[short]
    result = cli.set(node, name, "4e-8")
    assert not result.successful
    reason = result.reason
    assert reason.startswith(f"unknown parameter '{name}' for node {node}; "), reason
    assert "Invalid access to undeclared" not in reason
    if best:  # the closest first; every suggestion is a parameter of the node
        suggested = re.fullmatch(r".*; did you mean (.*)\?", reason).group(1).split(" or ")
        assert suggested[0] == repr(best) and all(n.strip("'") in specs for n in suggested), reason
    else:
        assert reason.endswith("its parameters: " + ", ".join(specs)), reason
    # the same words for the atomic service (ros2 param load uses set_parameters; a launch file may
    # not)
    from rclpy.parameter import Parameter

    atomic = cli.wait(
        cli.client(node).set_parameters_atomically([Parameter(name, value=4e-8)])
    ).result
    assert not atomic.successful and atomic.reason == reason
    assert not nodes[node].has_parameter(name)


@pytest.mark.parametrize(
    "short,name",
    [
        ("z_controller", "setpoint"),
        ("cantilever", "z_base"),
        ("scanner", "lines"),
        ("replay", "rate"),
    ],
)
def test_a_not_set_value_is_refused_naming_field_and_node_and_the_value_stays(
    afm_nodes, short, name
):
    """`ros2 param delete` sends a NOT_SET value; a parameter of these nodes always has one."""
    nodes, cli = afm_nodes
    node = _full(nodes, short)
    spec = node_specs()[short][name]
    before = cli.get(node, name)
    result = cli.delete(node, name)
    assert not result.successful
    assert result.reason == (
        f"{name} of node {node} cannot be unset (a NOT_SET value, as `ros2 param delete` "
        f"sends): it always has a value; allowed {spec.range_text()}"
    ), result.reason
    assert cli.get(node, name) == before
    assert nodes[node].has_parameter(name)


def test_out_of_range_reads_the_same_from_the_service_and_the_node(afm_nodes):
    """The node's stored descriptors carry no range, so the spec (not rclpy) words every
    refusal."""
    from rclpy.parameter import Parameter

    nodes, cli = afm_nodes
    node = nodes[_full(nodes, "cantilever")]
    remote = cli.set(_full(nodes, "cantilever"), "z_base", "2e-4")
    local = node.set_parameters([Parameter("z_base", value=2e-4)])[0]
    assert not remote.successful and not local.successful
    assert (
        remote.reason
        == local.reason
        == "z_base=0.0002 m is out of range; allowed range [-1e-06, 0.0001] m"
    )


def test_every_bounded_numeric_parameter_shows_its_range_in_describe(afm_nodes):
    nodes, cli = afm_nodes
    specs_by_node = node_specs()
    for node_name, node in nodes.items():
        specs = specs_by_node[node.get_name()]
        descriptors = cli.describe(node_name, list(specs))
        assert [d.name for d in descriptors] == list(specs)
        for (name, spec), d in zip(specs.items(), descriptors):
            assert d.type == TYPE_OF_KIND[spec.kind] and not d.dynamic_typing, (node_name, name)
            assert d.additional_constraints == f"allowed {spec.range_text()}", (node_name, name)
            if spec.kind is float:
                assert not d.integer_range and len(d.floating_point_range) == 1, (node_name, name)
                r = d.floating_point_range[0]
                assert (r.from_value, r.to_value, r.step) == (spec.low, spec.high, 0.0), (
                    node_name,
                    name,
                )
            elif spec.kind is int:
                assert not d.floating_point_range and len(d.integer_range) == 1, (node_name, name)
                r = d.integer_range[0]
                assert (r.from_value, r.to_value, r.step) == (spec.low, spec.high, 1), (
                    node_name,
                    name,
                )
            else:
                assert not d.floating_point_range and not d.integer_range
            if spec.low_open or spec.high_open:
                assert "open bound" in d.description, (node_name, name, d.description)
            # Node.describe_parameters (in process) agrees with the service
            assert node.describe_parameters([name])[0] == d


@pytest.mark.slow
def test_dump_then_load_round_trips_every_parameter_of_every_node(afm_nodes, tmp_path):
    """`ros2 param dump` then `ros2 param load` of that very file: every writable parameter is set
    again with its value and type unchanged; read-only ones are refused only as read-only."""
    from rclpy.parameter import parameter_dict_from_yaml_file

    nodes, cli = afm_nodes
    # non-default values first, so that the load is not a no-op
    for short, name, text in [
        ("cantilever", "z_base", "30e-9"),
        ("cantilever", "quality_factor", "30"),
        ("z_controller", "setpoint", "40e-9"),
        ("lockin", "time_constant", "1e-5"),
        ("replay", "rate", "2"),
    ]:
        assert cli.set(_full(nodes, short), name, text).successful
    for node_name, node in nodes.items():
        text = cli.dump(node_name)
        path = tmp_path / f"{node.get_name()}.yaml"
        path.write_text(text)
        names = list(yaml.safe_load(text)[node_name]["ros__parameters"])
        specs = node_specs()[node.get_name()]
        assert set(specs) <= set(names), node_name
        before = {n: cli.get(node_name, n) for n in names}
        types_before = {d.name: d.type for d in cli.describe(node_name, names)}
        read_only = {d.name for d in cli.describe(node_name, names) if d.read_only}
        sent = parameter_dict_from_yaml_file(str(path), True)
        results = cli.load(node_name, path)
        assert sorted(n for n, _ in results) == sorted(names)
        for name, result in results:
            if name in read_only:
                assert not result.successful and "read-only" in result.reason, (
                    node_name,
                    name,
                    result.reason,
                )
            else:
                assert result.successful, (node_name, name, result.reason)
        assert {n: cli.get(node_name, n) for n in names} == before, node_name
        assert {d.name: d.type for d in cli.describe(node_name, names)} == types_before, node_name
        # the issue: ros2 param load re-sends a dumped double such as 6e-08 as the string '6e-08'
        as_strings = [
            n
            for n, spec in specs.items()
            if spec.kind is float and sent[n].value.type == ParameterType.PARAMETER_STRING
        ]
        if node.get_name() == "cantilever":
            assert {"free_amplitude", "intermolecular_distance", "tip_radius", "z_base"} <= set(
                as_strings
            )
    dumped = yaml.safe_load((tmp_path / "cantilever.yaml").read_text())
    assert dumped[_full(nodes, "cantilever")]["ros__parameters"]["z_base"] == 30e-9


def test_start_values_are_converted_and_validated_like_live_values(ros_context):
    from rclpy.parameter import Parameter

    from afm_ros.nodes.z_controller_node import ZControllerNode

    node = ZControllerNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("setpoint", value="40e-9"),
            Parameter("p_gain", value=1),
            Parameter("enabled", value="off"),
        ],
    )
    try:
        assert node.get_parameter("setpoint").type_ == Parameter.Type.DOUBLE
        assert node.get_parameter("setpoint").value == 40e-9
        assert node.get_parameter("p_gain").type_ == Parameter.Type.DOUBLE
        assert node.get_parameter("p_gain").value == 1.0
        assert node.get_parameter("enabled").value is False
    finally:
        node.destroy_node()
    for bad, text in [
        (
            Parameter("setpoint", value="abc"),
            "setpoint='abc' is not a number; allowed range [0, 1e-06] m",
        ),
        (
            Parameter("setpoint", value=2e-6),
            "setpoint=2e-06 m is out of range; allowed range [0, 1e-06] m",
        ),
        (
            Parameter("p_gain", value=True),
            "p_gain=True is not a number; allowed range [0, 100] m/m",
        ),
    ]:
        with pytest.raises(ValueError) as info:
            ZControllerNode(context=ros_context, parameter_overrides=[bad])
        assert str(info.value) == text


def test_ros_args_p_and_params_file_values_are_typed(ros_context, ros_namespace, tmp_path, capfd):
    """`-p` and `--params-file` (parsed by rcl: 30 is an integer there) reach the node as doubles;
    an unknown key for the node is a warning naming key and node."""
    from rclpy.parameter import Parameter

    from afm_ros.nodes.cantilever_node import CantileverNode

    params = tmp_path / "p.yaml"
    params.write_text(
        "/**/cantilever:\n  ros__parameters:\n    quality_factor: 30\n    quality_factr: 31\n"
        "    steps_per_period: 240.0\n"
    )
    node = CantileverNode(
        context=ros_context,
        namespace=ros_namespace,
        cli_args=[
            "--ros-args",
            "--params-file",
            str(params),
            "-p",
            "z_base:=30e-9",
            "-p",
            "free_amplitude:=50e-9",
            "-p",
            "real_time_factor:=0.01",
        ],
    )
    try:
        assert node.get_parameter("quality_factor").type_ == Parameter.Type.DOUBLE
        assert node.get_parameter("quality_factor").value == 30.0
        assert node.get_parameter("steps_per_period").type_ == Parameter.Type.INTEGER
        assert node.get_parameter("steps_per_period").value == 240
        assert node.get_parameter("z_base").value == 30e-9
        assert node.get_parameter("free_amplitude").value == 50e-9
        assert not node.has_parameter("quality_factr")
    finally:
        node.destroy_node()
    err = capfd.readouterr().err
    assert re.search(
        f"unknown parameter 'quality_factr' for node {ros_namespace}/cantilever; did you mean "
        r"'quality_factor'.*\? \(from -p, --params-file or parameter_overrides: ignored\)",
        err,
    ), err
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**/cantilever:\n  ros__parameters:\n    quality_factor: 0.2\n")
    with pytest.raises(
        ValueError, match=r"^quality_factor=0\.2 is out of range; allowed range \(0\.5, 1e\+06\]$"
    ):
        CantileverNode(
            context=ros_context,
            namespace=ros_namespace,
            cli_args=["--ros-args", "--params-file", str(bad)],
        )


def test_coerce_table():
    """The conversion rules on their own (no ROS)."""
    from afm_ros.core.physics.parameters import ParamSpec
    from afm_ros.nodes.ros_params import coerce

    d = ParamSpec("d", 1.0, "m", "", -10.0, 1e3)
    i = ParamSpec("i", 1, "1", "", 0, 1000, kind=int)
    b = ParamSpec("b", True, "", "", kind=bool)
    s = ParamSpec("s", "", "", "", kind=str)
    for spec, value, expected in [
        (d, "30e-9", 30e-9),
        (d, "6e-08", 6e-8),
        (d, "1E3", 1000.0),
        (d, 3, 3.0),
        (d, " .5 ", 0.5),
        (d, "-4.", -4.0),
        (i, "220", 220),
        (i, 220.0, 220),
        (i, "2.2e2", 220),
        (i, "+7", 7),
        (b, "True", True),
        (b, "no", False),
        (b, "ON", True),
        (b, False, False),
        (s, "", ""),
        (s, 123, "123"),
        (s, 1.5, "1.5"),
        (s, True, "true"),
        (s, "6e-08", "6e-08"),
    ]:
        out = coerce(spec, value)
        assert out == expected and type(out) is type(expected), (spec.name, value, out)
    for spec, value in [
        (d, "nan"),
        (d, "inf"),
        (d, "1e3.0"),
        (d, "0x10"),
        (d, "1_000"),
        (d, False),
        (d, [1.0]),
        (i, 2.5),
        (i, "2.5"),
        (i, True),
        (b, 1),
        (b, "y"),
        (s, [1, 2]),
    ]:
        with pytest.raises(ValueError, match=f"^{spec.name}="):
            coerce(spec, value)


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
