"""``nanonis_node``: a Nanonis-compatible TCP server in front of an afm_ros instrument, so that lab
automation written for a Nanonis-controlled AFM (SPECS' nanonis_spm, nanonisTCP, ...) drives the
emulator unchanged.

Over ROS (the default) it drives the instrument's nodes running in its namespace (``ros2 run
afm_ros nanonis_node --ros-args -r __ns:=/afm1``) through the client
(:meth:`afm_ros.client.Microscope.connect`); ``--local`` serves an in-process instrument without
ROS (:meth:`~afm_ros.client.Microscope.local`, paced to real time). ``afm_instrument --nanonis``
starts the whole instrument with the server in one process. It listens on 127.0.0.1:6501 (the
protocol has no authentication: ``--address`` beyond loopback says so), serves up to 4
connections, executes their commands one at a time, saves every frame as ``.sxm`` and every Z
spectroscopy as ``.dat`` in the session folder, and stops on Ctrl-C with the frame being scanned
saved as far as it got (docs/nanonis.md).
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from afm_ros.client import ClientError, Microscope
from afm_ros.client.nanonis import serve, supported
from afm_ros.core.nanonis_server import DEFAULT_PORT
from afm_ros.tools.run_setup import RosArgs, make_run_folder

INTERRUPTED_STATUS = 130


def parse_args(argv):
    parser = argparse.ArgumentParser(
        prog="nanonis_node",
        description=__doc__.split("\n\n")[0],
        epilog="ROS arguments follow --ros-args, e.g. --ros-args -r __ns:=/afm1",
    )
    parser.add_argument(
        "--address",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; anything else lets the network drive the "
        "instrument: the protocol has no authentication)",
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="session folder for the .sxm and .dat files (default: a new afm_runs/<date>_<time>)",
    )
    parser.add_argument(
        "--idle",
        choices=["run", "hold"],
        default="run",
        help="run: simulated time passes while no command acts, as on a controller (default); "
        "hold: it passes only inside actions (a script's results depend on the script alone)",
    )
    parser.add_argument("--fm", action="store_true", help="the instrument runs FM (the pll node)")
    parser.add_argument(
        "--local",
        action="store_true",
        help="serve an in-process instrument without ROS (the PS/LDPE blend, a real instrument's "
        "imperfections), paced to real time",
    )
    parser.add_argument(
        "--ideal",
        action="store_true",
        help="with --local: no noise, drift, creep, hysteresis, tilt or tip wear",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        help="over ROS: seconds the instrument's nodes may take to answer (default 10)",
    )
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        parser.error(f"--port={args.port}: allowed 0-65535 (0: any free port)")
    if args.fm and args.local:
        parser.error("--fm with --local: the in-process FM instrument is afm_instrument --fm "
                     "--nanonis")  # fmt: skip
    if args.ideal and not args.local:
        parser.error("--ideal is for --local (over ROS the running nodes' parameters decide)")
    if not 0 < args.timeout <= 3600:
        parser.error(f"--timeout={args.timeout}: allowed (0, 3600] s")
    return args


def say(level: str, text: str) -> None:
    if level != "info" or text.startswith(("frame saved", "spectroscopy saved")):
        print(f"[{level}] {text}" if level != "info" else text, flush=True)


def main(argv=None) -> int:
    argv = sys.argv if argv is None else argv
    plain, ros = _split(argv[1:])
    options = parse_args(plain)
    namespace = RosArgs.parse(["--ros-args", *ros]).namespace if ros else ""
    served = afm = None
    try:
        folder = Path(options.out) if options.out else make_run_folder(None, namespace)
        if options.local:  # SIGTERM ends it as Ctrl-C does: what it made is saved
            signal.signal(signal.SIGTERM, _terminate_as_interrupt)
            afm = Microscope.local(ideal=options.ideal)
        else:
            _init_ros(["nanonis_node", "--ros-args", *ros] if ros else ["nanonis_node"])
            afm = Microscope.connect(
                namespace or "/", timeout=options.timeout, hold=options.idle == "hold"
            )
        served = serve(
            afm,
            folder,
            mode="fm" if options.fm else "am",
            address=options.address,
            port=options.port,
            idle=options.idle,
            pace=options.local,
            log=say,
        )
        where = "in process, no ROS" if options.local else f"ROS namespace {namespace or '/'}"
        print(
            f"Nanonis server on {options.address}:{served.port} ({len(supported())} commands, "
            f"{'FM' if options.fm else 'AM'}, {where}; no authentication); session folder "
            f"{served.session.folder}; Ctrl-C stops",
            flush=True,
        )
        while served.session.controller.failure == "" and _running(options.local):
            time.sleep(0.2)
        if not _running(options.local):
            return 0
        print(f"nanonis_node: the instrument stopped: {served.session.controller.failure}",
              file=sys.stderr)  # fmt: skip
        return 1
    except KeyboardInterrupt:
        return 0
    except (ClientError, OSError, ValueError) as exc:
        print(f"nanonis_node: {exc}", file=sys.stderr)
        return 1
    finally:
        if served is not None:
            try:
                served.close()
            except KeyboardInterrupt:
                print("nanonis_node: Ctrl-C again: stopped without waiting", file=sys.stderr)
            files = served.session.files
            print(f"nanonis_node: stopped; {len(files)} file(s) in {served.session.folder}",
                  flush=True)  # fmt: skip
        if afm is not None:
            afm.close()
        _shutdown_ros(options.local)


def _split(args: list[str]) -> tuple[list[str], list[str]]:
    """(own arguments, ROS arguments after --ros-args)."""
    if "--ros-args" in args:
        i = args.index("--ros-args")
        return args[:i], args[i + 1 :]
    return args, []


def _init_ros(args: list[str]) -> None:
    """rclpy with Ctrl-C / SIGTERM as a stop request (the server then saves what it has)."""
    from afm_ros.nodes import node_main  # noqa: PLC0415 - not for --local, which runs without ROS

    node_main.init(args)


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def _running(local: bool) -> bool:
    if local:
        return True  # Ctrl-C is a KeyboardInterrupt here
    from afm_ros.nodes import node_main  # noqa: PLC0415 - not for --local

    return node_main.running()


def _shutdown_ros(local: bool) -> None:
    if not local:
        import rclpy  # noqa: PLC0415 - not for --local

        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
