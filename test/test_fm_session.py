"""`afm_instrument --fm` end to end (the README's FM command, on a small frame): the PLL locks the free
cantilever and is centred on its resonance, the approach engages on df, the hold keeps df and the
amplitude at their setpoints, the frame of the cut PS/LDPE blend shows the islands in height and in
dissipation, and the .gwy file and the recorded session hold the FM channels and topics.

Expectations: the free drive of a self-excited cantilever is k A / Q (so Q = k A / F within RK4's own
loss, 4e-4 at Q 1e4 and 80 steps per period, test_fm_orbit); the island is 0.5 nm proud (the map) and
LDPE's adhesion hysteresis (H_retract - H = 7.1e-20 J) exceeds PS's (6.5e-20 J), so at the same df its
dissipation is the larger.
"""
from __future__ import annotations


import pytest

from afm_ros.core.imaging import DIRECTIONS, FM_CHANNELS
from afm_ros.formats.frames import channel_title
from afm_ros.formats.gwy import read_gwy
from afm_ros.formats.mcap_io import read_session

@pytest.fixture(scope="module")
def session(fm_session_run):
    """The shared small FM session (conftest: 16 x 4 pixels, as fast as possible, recorded)."""
    return fm_session_run


def test_free_lock_centres_the_pll_and_measures_q(session):
    _, s, text = session
    free = s["free"]
    assert free["pll_centre_before_Hz"] == 45000.0
    # the RK4 resonance: f0 (1 - theta^4 / 120) = 45000 - 0.0143 Hz, and the free far-field vdW at 100 nm
    assert abs(free["resonance_Hz"] - (45000.0 - 0.0143)) < 0.02
    assert free["amplitude_m"] == pytest.approx(5e-9, rel=2e-3)
    assert free["quality_factor_measured"] == pytest.approx(1e4 / (1 + 4.1e-4), rel=3e-3)
    assert "Q = k A / F" in text


def test_approach_engages_on_df_and_the_hold_keeps_both_setpoints(session):
    _, s, _ = session
    assert s["approach"]["engaged_s"] > 1.0  # 100 nm at 50 nm/s, from the end of the free lock
    hold = s["hold"]
    assert abs(hold["df"]["mean"] - s["df_setpoint_Hz"]) < 0.5
    assert hold["amplitude"]["mean"] == pytest.approx(5e-9, rel=1e-3, abs=0)
    # hysteresis_dmt dissipates out of contact: the drive is above the free drive, by E_ts / (pi A)
    assert hold["drive"]["mean"] > 1.5 * s["free"]["drive_N"]
    assert hold["dissipation_J"] > 0


def test_the_frame_shows_the_islands_in_height_and_dissipation(session):
    _, s, text = session
    by = s["image"]["by_material"]
    height = by["height"]["trace"]
    assert 0.3e-9 < height["contrast"] < 0.7e-9  # the 0.5 nm island (plus the vdW difference at equal df)
    assert by["dissipation"]["trace"]["contrast"] > 0  # LDPE's larger adhesion hysteresis
    assert by["drive"]["trace"]["contrast"] > 0
    assert all(n >= 3 for n in by["dissipation"]["trace"]["pixels"].values())
    assert "by material" in text and "contrast" in text


def test_the_gwy_file_and_the_session_hold_the_fm_channels(session):
    cwd, s, _ = session
    [gwy] = [cwd / f for f in s["image"]["files"] if f.endswith(".gwy")]
    channels = read_gwy(gwy).channels
    assert set(channels) >= {channel_title(c, d) for c in FM_CHANNELS for d in DIRECTIONS}
    assert s["recording"]["complete"] and s["recording"]["lost_samples"] == 0
    topics = {m.topic for m in read_session(cwd / s["recording"]["file"])}
    assert {"/pll/outputs", "/pll/excitation", "/lockin/outputs", "/z_controller/z_command"} <= topics
    assert s["withdraw"]["withdrawn_s"] > s["image"]["scan_start_s"]
