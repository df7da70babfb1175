"""The cantilever's `sample` parameter over its real parameter service (in-process DDS; issue 16,
points 17 and 18): one loading path with afm_study scan (a .gwy map is taken, not read as YAML),
a map above the size bound refused before it is read with the file, its size and the limit, and
a map too fine for the tip refused at set time instead of stopping the loop at the next chunk.
A refused value keeps the old one and the loop goes on."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import EXACT_PHYSICS
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from afm_ros.core.samples import from_file, rough
from afm_ros.formats.gwy import write_gwy
from afm_ros.nodes.cantilever_node import CantileverNode

pytestmark = pytest.mark.ros


def spin_until(executor, condition, timeout=120.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met in time"
        executor.spin_once(timeout_sec=0.01)


@pytest.fixture
def live(ros_context, ros_executor, ros_namespace):
    """A free-running cantilever (no feedback, no consumers) and a parameter client to it."""
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {
                **EXACT_PHYSICS,
                "real_time_factor": 0.0,
                "feedback_sync": "free",
                "run_until": -1.0,
            }.items()
        ],
    )
    user = Node("user", context=ros_context, namespace=ros_namespace)
    for n in (cantilever, user):
        ros_executor.add_node(n)
    client = AsyncParameterClient(user, f"{ros_namespace}/cantilever")
    spin_until(ros_executor, client.services_are_ready, 60)

    def set_sample(value: str):
        """Set `sample` through the service; (result, seconds until the answer)."""
        t0 = time.monotonic()
        future = client.set_parameters([Parameter("sample", value=value)])
        spin_until(ros_executor, future.done, 120)
        return future.result().results[0], time.monotonic() - t0

    def runs_on() -> None:
        t = cantilever.sim_time
        spin_until(ros_executor, lambda: cantilever.sim_time > t + 0.01, 60)
        assert cantilever.worker_error is None

    return cantilever, set_sample, runs_on, ros_executor


def test_a_gwy_map_is_taken_and_applied(live, tmp_path):
    cantilever, set_sample, runs_on, ex = live
    s = rough(pixels=(64, 64), size=(2e-6, 2e-6), correlation_length=0.1e-6, seed=3)
    path = tmp_path / "map.gwy"
    write_gwy(path, {"Height": (s.height, "m")}, s.size_x, s.size_y)
    result, _ = set_sample(str(path))
    assert result.successful, result.reason
    spin_until(ex, lambda: cantilever.engine.surface_info.get("sample") == str(path), 60)
    assert cantilever.engine.surface_info["description"] == from_file(path).description
    runs_on()


def _sparse_npy(path, rows, cols):
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1)))
    header["shape"] = (rows, cols)
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.truncate(f.tell() + rows * cols * 8)


def test_a_huge_map_is_refused_by_name_size_and_limit(live, tmp_path):
    cantilever, set_sample, runs_on, _ = live
    _sparse_npy(tmp_path / "huge.npy", 8192, 8192)  # 512 MiB
    (tmp_path / "huge.yaml").write_text("generator: from_file\npath: huge.npy\nsize: 1.0e-5\n")
    before = cantilever.get_parameter("sample").value
    result, _ = set_sample(str(tmp_path / "huge.yaml"))
    assert not result.successful
    assert (
        "huge.npy" in result.reason
        and "512.0 MiB" in result.reason
        and "at most 256 MiB" in result.reason
    )
    assert cantilever.get_parameter("sample").value == before
    runs_on()


def test_a_map_too_fine_for_the_tip_is_refused_at_set_time(live, tmp_path):
    """64 x 64 pixels over 2 nm: the 20 nm tip spans over a million pixel offsets. The dilation
    used to fail at the chunk boundary that applied the sample, which stopped the cantilever."""
    cantilever, set_sample, runs_on, _ = live
    np.save(tmp_path / "fine.npy", np.zeros((64, 64)))
    (tmp_path / "fine.yaml").write_text("generator: from_file\npath: fine.npy\nsize: 2.0e-9\n")
    result, _ = set_sample(str(tmp_path / "fine.yaml"))
    assert not result.successful
    assert "fine.yaml" in result.reason and "tip_radius" in result.reason, result.reason
    runs_on()
