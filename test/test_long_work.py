"""Work that takes long says so, with an honest estimate, before it starts (issue 28's guard):
the client's approach at a slow approach speed, the dataset plan after a frame 0 that compiled the
kernels, ``afm_instrument``'s bounded job, and the estimate of an approach against the time an
approach takes."""

import warnings

import pytest

from afm_ros.client import LongWork, Microscope
from afm_ros.core.approach import approach_time
from afm_ros.tools import dataset
from afm_ros.tools.afm_instrument import say_long_job
from afm_ros.tools.dataset import plan_text


def test_the_approach_estimate_is_the_time_an_approach_takes():
    """The estimate (cycles x (extend + retract + motor steps)) against a real approach from 5 um
    with a 3 um piezo: the surface is met within the last cycle's extension, so the approach
    takes less than the estimate and more than the estimate less one extension."""
    with Microscope.local(ideal=True) as afm:
        v = afm.get("z_controller", "z_min", "z_max", "approach_speed")
        estimate = approach_time({}, v["z_min"], v["z_max"])
        result = afm.approach()
    extension = (v["z_max"] - v["z_min"]) / v["approach_speed"]
    assert estimate - extension - 0.1 < result["duration_s"] < estimate


def test_a_slow_approach_says_how_long_before_it_starts():
    """At 10 nm/s the approach from 5 um takes two extensions of the 3 um piezo, 600 s simulated:
    said before anything moves (the warning made an error here, so the approach does not run)."""
    with Microscope.local(ideal=True, approach={"approach_speed": 1e-8}) as afm:
        with warnings.catch_warnings():
            warnings.simplefilter("error", LongWork)
            with pytest.raises(LongWork, match=r"approach\(\) simulates 600\.\d s"):
                afm.approach()
        assert afm.state()["t_s"] == 0.0 and afm.state()["stage"] == "withdrawn"


def test_the_dataset_plan_gives_no_estimate_from_a_frame_that_compiled_the_kernels(monkeypatch):
    """A frame 0 that compiled the kernels (a cold numba cache: 32 s instead of 0.5 s) says so and
    gives no estimate (it was 50 times too long); a warm one gives (frames - 1) x its time."""
    monkeypatch.setattr(dataset, "bytes_per_frame", lambda first: 200_000)  # the store's size
    spec, first = {"frames": 100000, "pixels": 64, "lines": 64}, {}
    cold = plan_text(spec, first, 32.0, 2, None, compiling=True)
    assert "including compiling the kernels" in cold and "of CPU" not in cold
    warm = plan_text(spec, first, 0.5, 2, None)
    assert "about 13.9 h of CPU" in warm and "on 2 workers" in warm


def test_afm_instruments_bounded_job_says_its_length(capsys):
    say_long_job(300.0, 1.0)
    assert "300 s simulated: about 0.0833 h" in capsys.readouterr().out
    say_long_job(30.0, 1.0)
    assert capsys.readouterr().out == ""  # under a minute: nothing to say
