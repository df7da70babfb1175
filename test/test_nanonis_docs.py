"""docs/nanonis.md agrees with the server's command declarations and signal table (both are
generated: ``python -m afm_ros.tools.config_gen nanonis``), and the server answers every command
issue 30 names."""

from pathlib import Path

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
