"""The recorder's and the replay's parameters (ParamSpec, SI units, no ROS import).

The nodes (afm_ros/nodes/recorder_node.py, replay_node.py) declare them; the session files they
write and read are :mod:`afm_ros.formats.mcap_io`.
"""

from __future__ import annotations

from afm_ros.core.physics.parameters import ParamSpec


def _specs(*specs: ParamSpec) -> dict[str, ParamSpec]:
    return {s.name: s for s in specs}


RECORDER_SPECS = _specs(
    ParamSpec(
        "output",
        "",
        "",
        "output .mcap file; empty = afm_session_<namespace>_<YYYY_MM_DD-HH_MM_SS>.mcap "
        "in the current working directory (no namespace part in the root namespace); an existing "
        "file is never overwritten: the first free name with _2, _3... is taken instead",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "topics",
        "",
        "",
        "comma-separated topic names or glob patterns (relative names resolve "
        "in the recorder's namespace); empty = every topic, or under a namespace every topic of "
        "that "
        "namespace plus /diagnostics and /rosout (/parameter_events is always recorded)",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "exclude",
        "",
        "",
        "comma-separated topic names or glob patterns never recorded",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "compression",
        "zstd",
        "",
        "chunk compression",
        kind=str,
        live=False,
        choices=("none", "lz4", "zstd"),
    ),
    ParamSpec(
        "chunk_size",
        4 * 1024 * 1024,
        "B",
        "uncompressed size at which a chunk is closed",
        low=1024,
        high=1 << 30,
        kind=int,
        live=False,
    ),
    ParamSpec(
        "flush_interval",
        1.0,
        "s",
        "wall-clock period of closing the current chunk and handing "
        "it to the OS; bounds the data lost by a SIGKILL",
        low=0.05,
        high=60.0,
        live=False,
    ),
    ParamSpec(
        "discovery_period",
        0.5,
        "s",
        "wall-clock period of looking for new topics and nodes",
        low=0.05,
        high=60.0,
        live=False,
    ),
    ParamSpec(
        "max_size",
        4e9,
        "B",
        "largest size of the file, summary included; when the next message "
        "would exceed it the recorder closes the file complete and stops recording (the "
        "instrument "
        "goes on); 0 = unlimited",
        low=0.0,
        high=1e15,
    ),
    ParamSpec(
        "min_free_space",
        1e9,
        "B",
        "free space the recording leaves on the file system: below it "
        "at the start the recorder refuses to start, and it stops (file closed complete) before "
        "the free space would drop below it; 0 = no check",
        low=0.0,
        high=1e15,
    ),
)

REPLAY_SPECS = _specs(
    ParamSpec("file", "", "", "the .mcap session to replay (required)", kind=str, live=False),
    ParamSpec(
        "rate",
        1.0,
        "1",
        "playback speed relative to the recording (2 = twice as fast)",
        low=0.0,
        high=1000.0,
        low_open=True,
    ),
    ParamSpec("loop", False, "", "start again at the end of the file", kind=bool, live=False),
    ParamSpec(
        "topics",
        "",
        "",
        "comma-separated recorded topic names or glob patterns to replay; empty = all",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "exclude",
        "/rosout,/parameter_events",
        "",
        "comma-separated recorded topics or glob patterns not replayed",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "topic_prefix",
        "",
        "",
        "namespace put in front of every replayed topic except /clock, "
        "e.g. /replay (ROS remapping rules apply as well)",
        kind=str,
        live=False,
    ),
    ParamSpec(
        "publish_clock",
        True,
        "",
        "publish /clock (simulated time): the recorded /clock, or the "
        "end time of each replayed deflection chunk if /clock was not recorded",
        kind=bool,
        live=False,
    ),
    ParamSpec(
        "start_delay",
        0.5,
        "s",
        "wall time between creating the publishers and the first message "
        "(lets subscribers connect)",
        low=0.0,
        high=60.0,
        live=False,
    ),
)
