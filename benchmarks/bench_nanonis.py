"""Nanonis server latency (prints JSON): ``python -m benchmarks.bench_nanonis [--repeats 500]``.

One in-process instrument (Microscope.local, ideal) behind the server on loopback, engaged, with a
256 x 256 frame scanned (the lock-in at 20 kS/s and 16 lines/s, so the frame takes 16 s
simulated). Side by side in one run, each read ``--repeats`` times, median and 99th percentile
[ms]:

- ``Signals.ValGet`` of Z: through the server with a minimal socket client (the codec of this
  package: what the server adds), with SPECS' ``nanonis_spm`` (its own parsing included), and the
  same read through the in-process client (``Microscope.signals()``), the baseline;
- ``Scan.FrameDataGrab`` of the 256 x 256 Z channel: the same three (the in-process read is
  ``frame_so_far`` and the array as float32);

with the controller idle ('hold': it waits for commands) and running in real time ('run', paced:
commands are taken between 2 ms chunks, so up to a chunk of wall time is added by design).
"""

from __future__ import annotations

import argparse
import json
import socket
import tempfile
import time

import numpy as np
from nanonis_spm import Nanonis

from afm_ros.client import Microscope
from afm_ros.client.nanonis import serve
from afm_ros.formats import nanonis_wire as w

PIXELS = LINES = 256
GRAB = [("name", "str"), ("data", "f2d"), ("up", "I")]


def stats(samples: list[float]) -> dict:
    ms = np.asarray(samples) * 1e3
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99))}


def timed(fn, repeats: int) -> dict:
    fn()  # warm
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return stats(out)


class RawClient:
    """The least a client can do: one request, read exactly the answer, parse with numpy."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def ask(self, name: str, fields, values, returns):
        body = w.encode(fields, values)
        self.sock.sendall(w.request_header(name, len(body)) + body)
        head = self._read(40)
        size = int.from_bytes(head[32:36], "big", signed=True)
        return w.parse_response(head + self._read(size), returns)

    def _read(self, n: int) -> bytes:
        parts, left = [], n
        while left:
            chunk = self.sock.recv(min(left, 1 << 20))
            if not chunk:
                raise ConnectionError("closed")
            parts.append(chunk)
            left -= len(chunk)
        return b"".join(parts)


def measure(served, afm, repeats: int) -> dict:
    raw = RawClient(served.port)
    spm = Nanonis(socket.create_connection(("127.0.0.1", served.port)))
    spm.returnDebugInfo(0)
    out = {
        "ValGet": {
            "in_process": timed(lambda: afm.signals()["z_m"], repeats),
            "server_raw_client": timed(
                lambda: raw.ask("Signals.ValGet", [("i", "i"), ("w", "I")], [14, 1], [("v", "f")]),
                repeats,
            ),
            "server_nanonis_spm": timed(lambda: spm.Signals_ValGet(14, 1), repeats),
        },
        "FrameDataGrab_256x256": {
            "in_process": timed(lambda: grab_in_process(afm), max(20, repeats // 10)),
            "server_raw_client": timed(
                lambda: raw.ask("Scan.FrameDataGrab", [("c", "I"), ("f", "I")], [14, 1], GRAB),
                max(20, repeats // 10),
            ),
            "server_nanonis_spm": timed(lambda: spm.Scan_FrameDataGrab(14, 1), 5),
        },
    }
    for read in out.values():
        base = read["in_process"]["median_ms"]
        read["server_adds_ms"] = read["server_raw_client"]["median_ms"] - base
    return out


def grab_in_process(afm) -> np.ndarray:
    """What FrameDataGrab hands over, read through the in-process client: the frame, its Z
    channel forward, float32 in scan order (an 'up' scan: as stored)."""
    return afm.frame_so_far()["height"].values[0].astype(np.float32)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=500)
    args = parser.parse_args(argv)
    result = {"repeats": args.repeats}
    afm = Microscope.local(ideal=True, lockin={"output_rate": 20e3})
    with tempfile.TemporaryDirectory() as folder:
        served = serve(afm, folder, port=0, idle="hold")
        try:
            n = RawClient(served.port)
            n.ask("AutoApproach.OnOffSet", [("on", "H")], [1], [])
            while n.ask("AutoApproach.OnOffGet", [], [], [("r", "H")])[1]["r"]:
                time.sleep(0.01)
            n.ask(
                "Scan.BufferSet",
                [("c", "i[]"), ("p", "i"), ("l", "i")],
                [[14, 5], PIXELS, LINES],
                [],
            )
            speed = [("a", "f"), ("b", "f"), ("c", "f"), ("d", "f"), ("k", "H"), ("r", "f")]
            n.ask("Scan.SpeedSet", speed, [0, 0, 1 / 32, 1 / 32, 2, 1], [])
            t0 = time.perf_counter()
            n.ask("Scan.Action", [("a", "H"), ("d", "I")], [0, 1], [])
            n.ask("Scan.WaitEndOfScan", [("t", "i")], [-1], [("t", "I"), ("p", "str")])
            result["scan_wall_s"] = time.perf_counter() - t0
            result["hold"] = measure(served, afm, args.repeats)
        finally:
            served.close()
        served = serve(afm, folder, port=0, idle="run", pace=True)
        try:
            result["run_paced"] = measure(served, afm, args.repeats)
        finally:
            served.close()
    afm.close()
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
