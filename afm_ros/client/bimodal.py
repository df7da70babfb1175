"""The bimodal instrument from Python: :class:`Bimodal` scans frames as xarray Datasets, over ROS
against the ``bimodal`` node of a namespace (:meth:`Bimodal.connect`) or in this process without
ROS (:meth:`Bimodal.local`, no rclpy import); the same values give the same frame, bit for bit.

A frame is one :class:`xarray.Dataset`: a variable per channel of
:data:`~afm_ros.core.bimodal_scan.CHANNELS` over ``y`` and ``x`` (the pixel centres [m], row 0 =
the first line; NaN where a pixel has no value), with its unit; attributes: the session's values,
``lines_done``, ``lines``, ``state`` (done, stopped), ``simulated_time_s`` and ``materials`` (a
JSON string: per material E* recovered and true [Pa], the bias, df2 [Hz], indentation [m], ...).

::

    from afm_ros.client.bimodal import Bimodal

    with Bimodal.local() as b:                      # or Bimodal.connect("/afm1")
        frame = b.frame(pixels=32, setpoint_ratio=0.7)
    print(frame.attrs["materials"])
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from afm_ros.client.errors import BadArgument, NoAnswer, WorkflowFailed
from afm_ros.core.bimodal_scan import (
    BIMODAL_SPECS,
    CHANNELS,
    check_with_sample,
    pixel_centres,
    rows_json,
    scan_of,
)

NAMES = (*BIMODAL_SPECS, "sample")  # what a client sets (output_directory is the node's own)
DONE = ("done", "stopped")


def frame_dataset(channels: dict, origin: tuple, size: float, attrs: dict):
    """An xarray Dataset of ``channels`` (name -> n x n array in :data:`CHANNELS`' units) on the
    pixel centres of an n x n frame of ``size`` [m] from ``origin``; ``attrs`` flattened for
    netCDF (bools as 0/1)."""
    import xarray as xr  # noqa: PLC0415 - a second to import: only when a frame is made

    n = next(iter(channels.values())).shape[1]
    x, y = pixel_centres(origin, size, n)
    data = {
        name: xr.DataArray(
            np.asarray(channels[name], dtype=np.float64), dims=("y", "x"), attrs={"units": unit}
        )
        for name, unit in CHANNELS.items()
    }
    flat = {k: (int(v) if isinstance(v, bool) else v) for k, v in attrs.items()}
    return xr.Dataset(
        data,
        coords={
            "y": ("y", y[: data["height"].shape[0]], {"units": "m"}),
            "x": ("x", x, {"units": "m"}),
        },
        attrs=flat,
    )


def _attrs(values: dict, lines_done: int, lines: int, state: str, t: float, rows: list) -> dict:
    return {
        **{k: values[k] for k in NAMES},
        "lines_done": lines_done,
        "lines": lines,
        "state": state,
        "simulated_time_s": t,
        "materials": json.dumps(rows),
    }


def _checked(values: dict) -> dict:
    """``values`` (session names and ``sample``) merged into the defaults and checked; BadArgument
    naming the field."""
    unknown = sorted(set(values) - set(NAMES))
    if unknown:
        raise BadArgument(
            f"{', '.join(unknown)}: not a bimodal parameter; known: {', '.join(NAMES)}"
        )
    try:
        return check_with_sample(values)
    except ValueError as exc:
        raise BadArgument(str(exc)) from None


class LocalBimodal:
    """The session in this process (core/bimodal_scan.py)."""

    def __init__(self, values: dict):
        self.values = _checked(values)

    def set_values(self, values: dict) -> None:
        self.values = _checked({**self.values, **values})

    def frame(self, progress):
        v = self.values
        scan = scan_of(v)
        frame = scan.run(progress)
        state = "done" if frame.lines_done == scan.n else "stopped"
        done = frame.lines_done
        channels = {name: frame.channels[name][:done] for name in CHANNELS}
        attrs = _attrs(v, done, scan.n, state, frame.simulated_time, rows_json(frame.rows))
        return frame_dataset(channels, frame.origin, frame.size, attrs)

    def close(self) -> None:
        pass


class RosBimodal:
    """The ``bimodal`` node of ``namespace`` (afm_ros.nodes.bimodal_node) over a RosLink."""

    def __init__(self, namespace: str, timeout: float):
        from afm_ros.client.ros_link import RosLink  # noqa: PLC0415 - rclpy only for this backend

        self.link = RosLink(namespace, timeout)
        self.link.wait_for_node("bimodal")

    @property
    def values(self) -> dict:
        return self.link.get_parameters("bimodal", list(NAMES))

    def set_values(self, values: dict) -> None:
        _checked({**self.values, **values})  # the same refusal as in process, before sending
        self.link.set_parameters("bimodal", values)

    def frame(self, progress):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: PLC0415
        from sensor_msgs.msg import Image  # noqa: PLC0415 - rclpy only for this backend

        link = self.link
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        images: dict = {}
        reports: list = []
        tables: list = []
        subs = [
            link.node.create_subscription(
                Image,
                link.resolve(f"bimodal/image/{name}"),
                lambda m, name=name: images.__setitem__(name, m),
                latched,
            )
            for name in CHANNELS
        ]
        subs += [
            link.on_progress(reports.append, "bimodal/progress"),
            link.on_progress(tables.append, "bimodal/materials"),
        ]
        try:
            values = self.values
            answer = link.trigger("bimodal/scan_frame", node="bimodal")
            number = int(answer.split()[1].rstrip(":"))  # "frame N: ..."
            try:
                end = self._follow(number, reports, progress)
            except KeyboardInterrupt:
                link.trigger("bimodal/stop", node="bimodal")  # the node keeps the lines done
                raise
            if end["state"] not in DONE:
                raise WorkflowFailed(f"bimodal frame {number} {end['state']}: {end['reason']}")
            stamp = int(round(end["simulated_s"] * 1e9))

            def arrived() -> bool:  # the images and the table of the frame's last line
                return (
                    len(images) == len(CHANNELS)
                    and all(
                        m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec == stamp
                        for m in images.values()
                    )
                    and any(t.get("frame") == number for t in tables)
                )

            if end["lines_done"]:
                link.spin_until(arrived, f"{link.resolve('bimodal/image/*')} of frame {number}")
            n = end["lines"]
            channels = {
                name: (
                    np.frombuffer(bytes(images[name].data), dtype="<f8").reshape(-1, n)
                    if end["lines_done"]
                    else np.empty((0, n))
                )
                for name in CHANNELS
            }
            rows = next((t["materials"] for t in reversed(tables) if t.get("frame") == number), [])
            attrs = _attrs(values, end["lines_done"], n, end["state"], end["simulated_s"], rows)
            return frame_dataset(channels, tuple(end["origin_m"]), end["size_m"], attrs)
        finally:
            for sub in subs:
                link.node.destroy_subscription(sub)

    def _follow(self, number: int, reports: list, progress) -> dict:
        """Serve callbacks until frame ``number`` ends; its last progress. NoAnswer if no line
        ends within the link's timeout."""
        shown, last = 0, time.monotonic()
        while True:
            mine = [r for r in reports if r.get("frame") == number]
            if mine and mine[-1]["lines_done"] > shown:
                shown, last = mine[-1]["lines_done"], time.monotonic()
                if progress is not None:
                    progress(shown, mine[-1]["lines"])
            if mine and mine[-1]["state"] != "scanning":
                return mine[-1]
            if time.monotonic() - last > self.link.timeout:
                raise NoAnswer(
                    f"{self.link.resolve('bimodal/progress')} (a line)", self.link.timeout
                )
            self.link.spin_for(0.05)

    def close(self) -> None:
        self.link.close()


class Bimodal:
    """Bimodal AM-FM / AM-AM frames (module docstring); SI units. Refusals raise
    :class:`~afm_ros.client.errors.BadArgument` naming the field before anything runs."""

    def __init__(self, backend):
        self._backend = backend

    @classmethod
    def local(cls, **values) -> "Bimodal":
        """The session in this process (no ROS); ``values``: parameters by name
        (:data:`~afm_ros.core.bimodal_scan.BIMODAL_SPECS`, ``sample``)."""
        return cls(LocalBimodal(values))

    @classmethod
    def connect(cls, namespace: str = "/", timeout: float = 30.0) -> "Bimodal":
        """The ``bimodal`` node in ``namespace``; ``timeout`` [s]: the longest it may take to be
        discovered, to answer, or to end a line."""
        if not isinstance(namespace, str):
            raise BadArgument(f"namespace={namespace!r} must be a string, e.g. '/afm1'")
        if not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and timeout > 0):
            raise BadArgument(f"timeout={timeout!r} s: allowed > 0")
        return cls(RosBimodal(namespace, float(timeout)))

    def set(self, **values) -> None:
        """Set parameters for the next frames (checked together; a refusal changes nothing)."""
        self._backend.set_values(values)

    def get(self, *names: str) -> dict:
        """Parameter values by name (all when none are named)."""
        values = self._backend.values
        unknown = [n for n in names if n not in values]
        if unknown:
            raise BadArgument(
                f"{', '.join(unknown)}: not a bimodal parameter; known: {', '.join(NAMES)}"
            )
        return {n: values[n] for n in (names or NAMES)}

    def frame(self, progress=None, **values):
        """Scan one frame (with ``values`` set first); ``progress(lines_done, lines)`` after each
        line. Ctrl-C stops the frame after its line under way."""
        if values:
            self.set(**values)
        return self._backend.frame(progress)

    def close(self) -> None:
        self._backend.close()

    def __enter__(self) -> "Bimodal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
