"""Every invalid physics input is rejected with an error naming the field and the allowed range."""

import math

import pytest

from afm_ros.core.physics import (
    ALL_PHYSICS_SPECS,
    CANTILEVER_SPECS,
    DMT_SPECS,
    Cantilever,
    DMTSample,
    Drive,
    Simulation,
    make_force_model,
)


def construct(name, value):
    """Build the physics object that takes spec ``name``; raise what it raises."""
    if name in DMT_SPECS:
        return DMTSample(**{name: value})
    if name in ("spring_constant", "resonance_frequency", "quality_factor"):
        return Cantilever(**{name: value})
    if name == "drive_frequency":
        # a valid resolution at any allowed drive frequency: resonance follows the drive
        return Drive(frequency=value)
    if name == "free_amplitude":
        return Drive.from_free_amplitude(Cantilever(), value)
    if name == "steps_per_period":
        return Simulation(steps_per_period=value)
    # z_base has no object of its own (the gap offset is z_base + z_piezo); nodes/tools validate it
    return CANTILEVER_SPECS[name].validate(value)


def bad_values(spec):
    """(label, value) pairs outside the spec's range or of the wrong type."""
    out = []
    if spec.low is not None:
        below = spec.low if spec.low_open else spec.low - max(abs(spec.low), 1.0) * 0.5
        out.append(("below", below))
    if spec.high is not None:
        above = spec.high if spec.high_open else spec.high + max(abs(spec.high), 1.0)
        out.append(("above", above))
    out += [
        ("nan", float("nan")),
        ("inf", float("inf")),
        ("string", "abc"),
        ("none", None),
        ("bool", True),
    ]
    if spec.kind is int:
        out.append(("fraction", spec.default + 0.5))
    return out


CASES = [
    (name, label, value)
    for name, spec in ALL_PHYSICS_SPECS.items()
    for label, value in bad_values(spec)
]


@pytest.mark.parametrize("name,label,value", CASES, ids=[f"{n}-{label}" for n, label, _ in CASES])
def test_bad_value_rejected_with_field_and_range(name, label, value):
    spec = ALL_PHYSICS_SPECS[name]
    with pytest.raises(ValueError) as info:
        construct(name, value)
    msg = str(info.value)
    assert name in msg
    if label in ("below", "above", "fraction"):
        assert spec.range_text() in msg  # e.g. "[0.001, 10000] N/m"


@pytest.mark.parametrize("name", list(ALL_PHYSICS_SPECS))
def test_boundary_and_default_values_accepted(name):
    spec = ALL_PHYSICS_SPECS[name]
    construct(name, spec.default)
    for bound, is_open in ((spec.low, spec.low_open), (spec.high, spec.high_open)):
        if bound is None:
            continue
        if not is_open:
            if name == "steps_per_period":
                continue  # the 100000 bound makes a large drive table; covered by validate() below
            construct(name, bound)
        spec.validate(bound if not is_open else (bound + spec.default) / 2)


def test_too_few_steps_per_resonance_period():
    cantilever = Cantilever(resonance_frequency=450e3)  # drive at 45 kHz, resonance 10x higher
    drive = Drive.from_free_amplitude(cantilever, 60e-9, frequency=45e3)
    with pytest.raises(ValueError) as info:
        Simulation(cantilever, drive, steps_per_period=100)  # 10 steps per resonance period
    msg = str(info.value)
    assert "steps_per_period=100" in msg and "resonance" in msg and "at least 20" in msg
    Simulation(cantilever, drive, steps_per_period=200)  # 20 per resonance period: accepted
    sim = Simulation(steps_per_period=200)
    with pytest.raises(ValueError, match="steps_per_period"):
        sim.reconfigure(cantilever=cantilever, drive=drive, steps_per_period=150)
    assert sim.steps_per_period == 200  # rejected change leaves the simulation as it was


def test_unknown_method_and_force_model():
    with pytest.raises(
        ValueError, match=r"method='rk5' is not known; allowed: euler, verlet, rk4, rk4_frozen"
    ):
        Simulation(method="rk5")
    with pytest.raises(ValueError, match=r"force_model='lj' is not known; allowed: 'none', 'dmt'"):
        make_force_model("lj")


@pytest.mark.parametrize("force", [-1e-9, 1.0, float("nan"), "x"])
def test_bad_drive_force(force):
    with pytest.raises(ValueError, match=r"drive_force=.*allowed range \[0, 0.001\] N"):
        Drive(force=force)


def test_bad_simulation_inputs():
    with pytest.raises(ValueError, match="z_offset"):
        Simulation(z_offset=math.nan)
    sim = Simulation()
    with pytest.raises(ValueError, match="nsteps"):
        sim.advance(-1)
    with pytest.raises(ValueError, match="decimation"):
        sim.advance(10, decimation=0)
    with pytest.raises(ValueError, match="drive_phase"):
        Drive(phase=math.inf)
