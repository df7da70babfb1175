"""docs/nanonis.md agrees with the server's command declarations and signal table (both are
generated: ``python -m afm_ros.tools.config_gen nanonis``), and the server answers every command
issue 30 names."""

from pathlib import Path

import pytest

from afm_ros.client.nanonis import COMMANDS
from afm_ros.client.nanonis.commands import command_table
from afm_ros.client.nanonis.signals import signal_table

DOC = Path(__file__).resolve().parents[1] / "docs" / "nanonis.md"

# the commands the issue asks for, by module (its own list)
ASKED = {
    "Scan": "Action StatusGet FrameSet FrameGet BufferSet BufferGet PropsSet PropsGet SpeedSet "
    "SpeedGet WaitEndOfScan FrameDataGrab",
    "ZCtrl": "OnOffSet OnOffGet SetpntSet SetpntGet GainSet GainGet ZPosSet ZPosGet LimitsGet "
    "StatusGet CtrlListGet ActiveCtrlSet Withdraw Home",
    "FolMe": "XYPosSet XYPosGet SpeedSet SpeedGet",
    "Motor": "StartMove StopMove PosGet",
    "AutoApproach": "Open OnOffSet OnOffGet",
    "ZSpectr": "Open Start Stop StatusGet PropsSet PropsGet ChsSet ChsGet RangeSet RangeGet "
    "TimingSet TimingGet",
    "Signals": "NamesGet ValGet ValsGet RangeGet",
    "Piezo": "RangeGet TiltSet TiltGet DriftCompSet DriftCompGet",
    "PLL": "CenterFreqSet CenterFreqGet FreqShiftGet ExcitationSet ExcitationGet OutOnOffSet "
    "OutOnOffGet AmpCtrlSetpntSet AmpCtrlSetpntGet AmpCtrlOnOffSet AmpCtrlOnOffGet AmpCtrlGainSet "
    "AmpCtrlGainGet PhasCtrlOnOffSet PhasCtrlOnOffGet PhasCtrlGainSet PhasCtrlGainGet",
    "PLLFreqSwp": "Open ParamsSet ParamsGet Start",
    "OsciHR": "ChSet ChGet SamplesSet SamplesGet OsciDataGet",
    "Util": "SessionPathGet VersionGet",
}


def test_every_asked_command_is_answered():
    missing = [
        f"{module}.{name}"
        for module, names in ASKED.items()
        for name in names.split()
        if f"{module}.{name}" not in COMMANDS
    ]
    assert not missing


def test_the_docs_tables_are_the_generated_ones():
    text = DOC.read_text()
    assert command_table() in text, "docs/nanonis.md: regenerate the command table"
    assert signal_table() in text, "docs/nanonis.md: regenerate the signal table"


def test_every_command_says_what_it_does():
    from afm_ros.client.nanonis.commands import describe

    assert not [name for name, cmd in COMMANDS.items() if not describe(cmd)]


@pytest.mark.slow
def test_the_readmes_nanonis_script_scans_a_frame(tmp_path, capsys):
    """The README's script, as written (its port aside), against an in-process instrument."""
    import re

    import numpy as np

    from afm_ros.client import Microscope
    from afm_ros.client.nanonis import serve

    readme = (DOC.parents[1] / "README.md").read_text()
    section = readme.split("## Speaking Nanonis", 1)[1]
    script = section.split("```python\n", 1)[1].split("```", 1)[0]
    with Microscope.local(ideal=True) as afm:
        served = serve(afm, tmp_path, port=0, idle="hold")
        try:
            namespace = {}
            exec(re.sub(r"\b6501\b", str(served.port), script), namespace)
        finally:
            served.close()
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert printed.endswith("Scan001.sxm") and (tmp_path / "Scan001.sxm").exists()
    z = np.asarray(namespace["z"])
    assert z.shape == (64, 64) and np.isfinite(z).all()
