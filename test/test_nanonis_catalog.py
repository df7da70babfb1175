"""Commands the emulator does not model are still answered in the layout the clients parse: the
catalog (afm_ros/formats/nanonis_catalog.json, every command SPECS' nanonis_spm knows with the
response fields it reads) is the installed client's own, and for every one of its commands the
server does not implement, nanonis_spm's own parser reads the server's answer as a refusal (the
error text) with empty values, never misreading the text as data."""

import runpy
import socket
from pathlib import Path

import pytest

from afm_ros.client import Microscope
from afm_ros.client.nanonis import COMMANDS, serve
from afm_ros.formats import nanonis_catalog
from afm_ros.formats.nanonis_wire import request_header

ROOT = Path(__file__).resolve().parents[1]


def test_the_catalog_is_the_installed_clients():
    script = runpy.run_path(str(ROOT / "scripts" / "nanonis_catalog.py"))
    assert script["catalog"]() == nanonis_catalog.commands()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    afm = Microscope.local(ideal=True)
    served = serve(afm, tmp_path_factory.mktemp("catalog"), port=0, idle="hold")
    yield served
    served.close()
    afm.close()


def _receive(sock, n):
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        assert chunk, "closed"
        out += chunk
    return out


# nanonis_spm 1.0.9's own response codes for these cannot be parsed whatever a server answers:
# '*-c' after a string (no length before it), '+*c' (not a struct code), '*+d' (a float count)
CLIENT_CANNOT_PARSE = {
    "HSSwp.SaveBasenameGet": "two '*-c' in a row",
    "HSSwp.SwpChSigListGet": "'+*c' is not a code its parser knows",
    "PLLSignalAnlzr.OsciDataGet": "'*+d' takes its count from a float",
}


def test_every_unmodelled_command_is_a_refusal_nanonis_spm_parses(server):
    from nanonis_spm import Nanonis

    unmodelled = sorted(set(nanonis_catalog.commands()) - set(COMMANDS) - set(CLIENT_CANNOT_PARSE))
    assert len(unmodelled) > 500
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as sock:
        parser = Nanonis(sock)
        parser.returnDebugInfo(0)
        for name in unmodelled:
            sock.sendall(request_header(name, 0))
            head = _receive(sock, 40)
            assert head[:32].rstrip(b"\0").decode() == name
            body = _receive(sock, int.from_bytes(head[32:36], "big"))
            codes = nanonis_catalog.commands()[name]
            error, _, values = parser.parseGeneralResponse(body, codes)
            assert error.startswith(f"{name}: a Nanonis command this emulator does not model"), (
                name
            )


def test_what_afspm_sets_at_start_up_is_accepted():
    """afspm's Nanonis translator configures bias spectroscopy and polls its status when it
    starts: the settings are kept, the status reads not running, a start is refused."""
    afm = Microscope.local(ideal=True)
    import tempfile

    from nanonis_spm import Nanonis

    with tempfile.TemporaryDirectory() as folder:
        served = serve(afm, folder, port=0, idle="hold")
        try:
            with socket.create_connection(("127.0.0.1", served.port), timeout=60) as sock:
                n = Nanonis(sock)
                n.returnDebugInfo(0)
                assert n.BiasSpectr_PropsSet(0, 1, 1, 128, 0.0, 1, 2)[0] == ""
                assert served.session.bias_spectroscopy["points"] == 128
                error = n.BiasSpectr_Start(1, "")[0]
                assert "does not model" in error
        finally:
            served.close()
    afm.close()
