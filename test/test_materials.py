"""The materials table (issue 9): every entry validates against the DMT specs and names its
sources; lookup errors name the field and the choices; explicit overrides win over the table."""

import dataclasses
import math

import pytest

from afm_ros.core.physics.forces import make_force_model
from afm_ros.core.physics.materials import MATERIALS, SOURCES, Material, material, sample_for
from afm_ros.core.physics.parameters import DMT_SPECS, DMTSample


def test_table_has_the_required_materials():
    for name in ("seed", "polystyrene", "ldpe", "silicon", "silicon_oxide", "mica"):
        assert name in MATERIALS


@pytest.mark.parametrize("name", list(MATERIALS))
def test_every_material_validates_and_names_its_sources(name):
    m = MATERIALS[name]
    assert m.name == name
    assert Material(**dataclasses.asdict(m)) == m  # passes the validation again
    assert DMT_SPECS["sample_youngs_modulus"].validate(m.youngs_modulus) == m.youngs_modulus
    assert DMT_SPECS["sample_poisson_ratio"].validate(m.poisson_ratio) == m.poisson_ratio
    assert DMT_SPECS["hamaker_constant"].validate(m.hamaker_constant) == m.hamaker_constant
    assert m.viscosity >= 0 and m.hamaker_constant_retract >= 0
    assert m.note and m.sources(), "every entry needs a note naming at least one source key"
    assert all(key in SOURCES for key in m.sources())
    sample, eta, h_r = sample_for(m)
    assert isinstance(sample, DMTSample)
    for model in ("dmt", "viscoelastic_dmt", "hysteresis_dmt"):
        make_force_model(model, sample, viscosity=eta, hamaker_retract=h_r).packed()


def test_seed_is_the_dmt_spec_defaults():
    seed = MATERIALS["seed"]
    sample, eta, h_r = sample_for("seed")
    assert sample == DMTSample()  # every field: the seed notebook's sample
    assert (seed.youngs_modulus, seed.poisson_ratio, seed.hamaker_constant) == (
        DMT_SPECS["sample_youngs_modulus"].default,
        DMT_SPECS["sample_poisson_ratio"].default,
        DMT_SPECS["hamaker_constant"].default,
    )
    assert eta == 0.0 and h_r == seed.hamaker_constant  # conservative, as the seed


def test_unknown_material_names_the_field_and_the_choices():
    with pytest.raises(ValueError, match="material") as info:
        material("teflon")
    for name in MATERIALS:
        assert repr(name) in str(info.value)
    with pytest.raises(ValueError, match="material"):
        sample_for("teflon")


def test_explicit_values_override_the_material():
    ps = MATERIALS["polystyrene"]
    sample, eta, h_r = sample_for(
        "polystyrene",
        viscosity=1.5,
        hamaker_constant_retract=0.0,
        sample_youngs_modulus=1e9,
        tip_radius=5e-9,
    )
    assert (eta, h_r, sample.sample_youngs_modulus, sample.tip_radius) == (1.5, 0.0, 1e9, 5e-9)
    assert (
        sample.hamaker_constant == ps.hamaker_constant
    )  # untouched fields keep the table's value
    assert sample.sample_poisson_ratio == ps.poisson_ratio
    # a tip material: its E and nu, and the combining relation sqrt(H_tip H_sample)
    sample, _, h_r = sample_for("polystyrene", tip="silicon")
    si = MATERIALS["silicon"]
    assert (sample.tip_youngs_modulus, sample.tip_poisson_ratio) == (
        si.youngs_modulus,
        si.poisson_ratio,
    )
    assert sample.hamaker_constant == pytest.approx(
        math.sqrt(si.hamaker_constant * ps.hamaker_constant), rel=1e-15, abs=0
    )
    assert (
        sample_for("polystyrene", tip="silicon", hamaker_constant=1e-20)[0].hamaker_constant
        == 1e-20
    )


def test_bad_values_are_rejected_by_name():
    seed = MATERIALS["seed"]
    for field, value, named in (
        ("viscosity", -1.0, "viscosity"),
        ("viscosity", math.nan, "viscosity"),
        ("hamaker_constant_retract", -1e-20, "hamaker_constant_retract"),
        ("hamaker_constant_retract", 1.0, "hamaker_constant_retract"),
        ("youngs_modulus", 1.0, "sample_youngs_modulus"),
        ("poisson_ratio", 0.6, "sample_poisson_ratio"),
        ("hamaker_constant", 1e-15, "hamaker_constant"),
    ):
        with pytest.raises(ValueError, match=named):
            dataclasses.replace(seed, **{field: value})
    with pytest.raises(ValueError, match="viscosity"):
        sample_for("seed", viscosity=-2.0)
    with pytest.raises(ValueError, match="unknown override"):
        sample_for("seed", viscosityy=2.0)
