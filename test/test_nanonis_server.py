"""The Nanonis server core (afm_ros.core.nanonis_server, no ROS) against hostile clients, over
real loopback sockets: malformed headers, a body size that does not match, a huge body size, a
client gone mid-message, one that never reads its answers, a fifth connection, unknown commands,
bad values. Each is answered or dropped as documented and logged, and the other connections keep
being served meanwhile, by a trivial dispatcher and by the instrument's own session (an in-process
instrument: a refused value keeps the old one)."""

import socket
import struct
import threading
import time

import pytest

from afm_ros.core.nanonis_server import NanonisServer
from afm_ros.formats import nanonis_wire as w

DEADLINE_S = 30.0  # [s] wall, generous: nothing here waits on a speed


def echo(name: str, body: bytes) -> bytes:
    """A dispatcher that answers with the body's length (and 'Big.Get' with 4 MB of floats)."""
    if name == "Big.Get":
        return w.response(name, w.encode([("a", "f[]")], [[0.0] * (1 << 20)]))
    if name == "Boom.Get":
        raise RuntimeError("boom")
    return w.response(name, w.encode([("n", "i")], [len(body)]))


@pytest.fixture
def server():
    logs = []
    srv = NanonisServer(
        echo, port=0, send_timeout=0.5, log=lambda level, text: logs.append((level, text))
    ).start()
    srv.logs = logs
    yield srv
    srv.close()


def connect(srv) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", srv.port), timeout=DEADLINE_S)
    return sock


def read_response(sock) -> tuple[str, bytes]:
    head = b""
    while len(head) < 40:
        chunk = sock.recv(40 - len(head))
        if not chunk:
            raise ConnectionError("closed")
        head += chunk
    (size,) = struct.unpack(">i", head[32:36])
    body = b""
    while len(body) < size:
        chunk = sock.recv(size - len(body))
        if not chunk:
            raise ConnectionError("closed mid-body")
        body += chunk
    return head[:32].rstrip(b"\0").decode(), body


def ask(sock, name: str, body: bytes = b"") -> tuple[str, bytes]:
    sock.sendall(w.request_header(name, len(body)) + body)
    return read_response(sock)


def closed(sock) -> bool:
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def until(condition, what: str) -> None:
    end = time.monotonic() + DEADLINE_S
    while not condition():
        assert time.monotonic() < end, what
        time.sleep(0.01)


def test_a_request_is_answered_with_its_name_and_an_empty_error_section(server):
    with connect(server) as s:
        name, body = ask(s, "Any.Thing", b"abc")
        assert name == "Any.Thing" and body == struct.pack(">i", 3) + bytes(8)


def test_a_malformed_header_is_answered_then_its_connection_closed_and_the_others_go_on(server):
    with connect(server) as good, connect(server) as bad:
        bad.sendall(b"\xff" * 40)
        name, body = read_response(bad)
        assert b"malformed request" in body and closed(bad)
        assert ask(good, "Still.Here")[0] == "Still.Here"
    assert any("not ASCII" in text for _, text in server.logs)


def test_a_huge_body_size_is_refused_before_any_of_it_is_read(server):
    with connect(server) as s:
        s.sendall(w.request_header("Scan.Action", 2**31 - 1))  # and no body at all
        name, body = read_response(s)
        assert name == "Scan.Action" and b"exceeds the server's limit" in body
        assert closed(s)


def test_a_client_gone_mid_message_ends_only_its_own_connection(server):
    with connect(server) as good:
        for partial in (b"Scan.Act", w.request_header("Scan.Action", 6) + b"\x00\x01"):
            s = connect(server)
            s.sendall(partial)
            s.close()
            assert ask(good, "Still.Here")[0] == "Still.Here"
    until(lambda: server.clients == 0, "the connections gone mid-message are closed")
    until(
        lambda: sum("mid-message" in text for _, text in server.logs) == 2,
        "both logged as gone mid-message",
    )


def test_a_client_that_never_reads_is_dropped_and_does_not_stall_the_others(server):
    slow = connect(server)
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    for _ in range(8):  # 32 MB of answers into a socket nobody reads
        slow.sendall(w.request_header("Big.Get", 0))
    with connect(server) as good:
        t0 = time.monotonic()
        for _ in range(20):
            assert ask(good, "Quick.Get")[0] == "Quick.Get"
        assert time.monotonic() - t0 < DEADLINE_S
        until(
            lambda: any("did not read" in text for _, text in server.logs),
            "the slow client is dropped",
        )
    slow.close()


def test_a_fifth_connection_is_closed_at_once_and_the_four_keep_working(server):
    four = [connect(server) for _ in range(4)]
    for s in four:
        ask(s, "Hello.Get")
    fifth = connect(server)
    assert closed(fifth)
    for s in four:
        assert ask(s, "Hello.Get")[0] == "Hello.Get"
        s.close()
    assert any("4 clients are connected" in text for _, text in server.logs)
    until(lambda: server.clients == 0, "the four closed")
    with connect(server) as again:  # a free slot serves again
        assert ask(again, "Hello.Get")[0] == "Hello.Get"


def test_a_request_without_the_response_flag_is_executed_silently(server):
    with connect(server) as s:
        s.sendall(w.request_header("Quiet.Set", 0, respond=False))
        assert ask(s, "Loud.Get")[0] == "Loud.Get"  # the next answer is the next request's


def test_a_dispatcher_fault_fails_its_command_not_the_connection(server):
    with connect(server) as s:
        name, body = ask(s, "Boom.Get")
        assert name == "Boom.Get" and b"internal error: boom" in body
        assert ask(s, "After.Get")[0] == "After.Get"


def test_beyond_loopback_only_when_asked_and_with_a_warning():
    logs = []
    srv = NanonisServer(echo, address="0.0.0.0", port=0, log=lambda lv, t: logs.append((lv, t)))
    srv.start()
    try:
        assert any(lv == "warn" and "no authentication" in t for lv, t in logs)
    finally:
        srv.close()
    default = NanonisServer(echo, port=0).start()
    try:
        assert default.bound == ("127.0.0.1", default.port)
    finally:
        default.close()
    with pytest.raises(ValueError, match="port"):
        NanonisServer(echo, port=70000)


# --- the instrument's own session behind the server
# -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def instrument(tmp_path_factory):
    from afm_ros.client import Microscope
    from afm_ros.client.nanonis import serve

    afm = Microscope.local(ideal=True)
    served = serve(afm, tmp_path_factory.mktemp("nanonis"), port=0, idle="hold")
    yield served
    served.close()
    afm.close()


def call(sock, name, fields, values, returns):
    name_back, body = ask(sock, name, w.encode(fields, values))
    assert name_back == name
    _, out, error = w.parse_response(w.response_header(name, len(body)) + body, returns)
    return out, error


def test_a_refused_value_names_its_field_and_range_and_keeps_the_old_one(instrument):
    with socket.create_connection(("127.0.0.1", instrument.port), timeout=DEADLINE_S) as s:
        before, error = call(s, "ZCtrl.SetpntGet", [], [], [("v", "f")])
        assert error == ""
        _, error = call(s, "ZCtrl.SetpntSet", [("v", "f")], [2e-6], [])
        assert "ZCtrl.SetpntSet" in error and "setpoint" in error and "1e-06" in error
        after, _ = call(s, "ZCtrl.SetpntGet", [], [], [("v", "f")])
        assert after == before
        _, error = call(
            s, "Scan.BufferSet", [("c", "i[]"), ("p", "i"), ("l", "i")], [[0], 8, 8], []
        )
        assert "channel 0" in error and "image channel" in error


def test_malformed_arguments_and_unknown_commands_are_errors_and_the_instrument_goes_on(
    instrument,
):
    with socket.create_connection(("127.0.0.1", instrument.port), timeout=DEADLINE_S) as s:
        _, error = call(s, "Signals.ValGet", [("i", "i")], [14], [("v", "f")])  # one field short
        assert "malformed arguments" in error and "wait_newest" in error
        name, body = ask(s, "Bias.Set", struct.pack(">f", 1.0))  # a Nanonis command, not modelled
        assert name == "Bias.Set" and b"a Nanonis command this emulator does not model" in body
        name, body = ask(s, "Foo.Bar")  # no Nanonis command at all
        assert name == "Foo.Bar" and b"not a command of this emulator" in body
        values, error = call(s, "Signals.ValGet", [("i", "i"), ("w", "I")], [16, 1], [("v", "f")])
        assert error == "" and values["v"] >= 0.0  # the simulated time, still answered


def test_every_connection_is_served_while_another_waits_for_a_long_action(instrument):
    """A connection blocked in a long command (here a sweep, PLLFreqSwp.Start) does not stop the
    others: their short commands are executed between the action's chunks."""
    answers = []

    def tune():
        with socket.create_connection(("127.0.0.1", instrument.port), timeout=120) as s:
            out, error = call(
                s,
                "PLLFreqSwp.Start",
                [("m", "i"), ("g", "I"), ("u", "I")],
                [1, 0, 1],
                [
                    ("c", "strarr"),
                    ("d", "f2d"),
                    ("f0", "d"),
                    ("q", "d"),
                    ("p", "f"),
                    ("r", "f"),
                    ("n", "i"),
                    ("m", "i"),
                ],  # fmt: skip
            )
            answers.append((out, error))

    thread = threading.Thread(target=tune)
    thread.start()
    with socket.create_connection(("127.0.0.1", instrument.port), timeout=DEADLINE_S) as s:
        seen = []
        while thread.is_alive():
            values, error = call(
                s, "Signals.ValGet", [("i", "i"), ("w", "I")], [16, 1], [("v", "f")]
            )
            assert error == ""
            seen.append(values["v"])
        thread.join()
    (out, error), = answers  # fmt: skip
    assert error == "" and out["f0"] == pytest.approx(45e3, rel=1e-3)
    assert len(set(seen)) > 3  # the simulated time moved while the sweep ran
