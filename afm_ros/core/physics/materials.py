"""Named sample materials for the tip-sample force models (no ROS, SI units).

One table, :data:`MATERIALS`, of :class:`Material` entries: Young's modulus [Pa], Poisson ratio
[1], Hamaker constant on approach and on retract [J] and Kelvin-Voigt viscosity [Pa s]. Every
number and its source is listed in ``docs/materials.md``; the short keys in each entry's ``note``
name the sources in :data:`SOURCES`. Values marked *illustrative* are picks inside a wide
literature range (the range is given in the note), chosen for the reason stated there.

Which model uses which column: ``dmt`` uses E, nu and H; ``viscoelastic_dmt`` adds the viscosity;
``hysteresis_dmt`` adds H_retract (its H on retraction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from afm_ros.core.physics.parameters import DMT_SPECS, DMTSample

SOURCES: dict[str, str] = {
    "seed": "the seed notebook's DMT sample (DMT_SPECS defaults): E_s 70 MPa, nu 0.3, H 6.4e-20 J",
    "israelachvili": "J. N. Israelachvili, Intermolecular and Surface Forces, 3rd ed. (Academic "
    "Press 2011), "
    "Table 13.2 (Hamaker constants of solids across vacuum)",
    "walstra": "P. Walstra, Physical Chemistry of Foods (Marcel Dekker 2003), Table 12.2 (Hamaker "
    "constants "
    "across vacuum: polystyrene 65e-21 J, solid paraffin 71e-21 J, glass ~90e-21 J)",
    "bergstrom": "L. Bergstrom, Hamaker constants of inorganic materials, Adv. Colloid Interface "
    "Sci. 70, "
    "125-169 (1997) (Lifshitz values for silica, silicon, muscovite mica, ...)",
    "polymer_handbook": "polymer handbooks (e.g. J. E. Mark (ed.), Physical Properties of "
    "Polymers Handbook, "
    "2nd ed., Springer 2007): PS E 3.0-3.5 GPa, nu 0.33-0.35; LDPE E 0.1-0.3 GPa, nu ~0.45-0.49",
    "hopcroft": "M. A. Hopcroft, W. D. Nix, T. W. Kenny, What is the Young's modulus of silicon?, "
    "J. Microelectromech. Syst. 19, 229 (2010): E 130-188 GPa, nu 0.064-0.36 by direction",
    "silica": "fused silica datasheets / glass handbooks: E 72-73 GPa, nu 0.16-0.17",
    "mica": "muscovite elastic constants (e.g. McNeil and Grimsditch, J. Phys.: Condens. Matter "
    "5, 1681 "
    "(1993)): strongly anisotropic, c33 ~ 60 GPa normal to the cleavage plane, ~170-180 GPa in "
    "plane",
    "kelvin_voigt": "E. A. Lopez-Guerra and S. D. Solares, Modeling viscoelasticity through "
    "spring-dashpot "
    "models in intermittent-contact AFM, Beilstein J. Nanotechnol. 5 (2014), "
    "doi:10.3762/bjnano.5.224; R. Garcia, Amplitude Modulation AFM (Wiley 2010): the "
    "Kelvin-Voigt eta is a model parameter fitted per sample, not a tabulated constant",
    "dforce": "dForce 2.0 (Gisbert and Garcia, Beilstein J. Nanotechnol. 14, 2023): adhesion "
    "hysteresis as "
    "different surface energies (here Hamaker constants) on approach and retract",
    "illustrative": "illustrative value: see the note for the literature range and why this pick",
}


@dataclass(frozen=True)
class Material:
    """A sample material: E [Pa], nu [1], H approach [J], H retract [J], Kelvin-Voigt eta [Pa
    s]."""

    name: str
    youngs_modulus: float
    poisson_ratio: float
    hamaker_constant: float
    hamaker_constant_retract: float
    viscosity: float
    note: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name={self.name!r} must be a non-empty string")
        for attr, spec in (
            ("youngs_modulus", "sample_youngs_modulus"),
            ("poisson_ratio", "sample_poisson_ratio"),
            ("hamaker_constant", "hamaker_constant"),
        ):
            object.__setattr__(self, attr, DMT_SPECS[spec].validate(getattr(self, attr)))
        for attr, unit in (("hamaker_constant_retract", "J"), ("viscosity", "Pa s")):
            value = getattr(self, attr)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or value < 0.0
            ):
                raise ValueError(f"{attr}={value!r} {unit} must be a finite number >= 0")
            object.__setattr__(self, attr, float(value))
        h_max = DMT_SPECS["hamaker_constant"].high
        if self.hamaker_constant_retract > h_max:
            raise ValueError(
                f"hamaker_constant_retract={self.hamaker_constant_retract!r} J is out of range; "
                f"allowed range [0, {h_max:g}] J"
            )

    def sources(self) -> list[str]:
        """The keys of :data:`SOURCES` named in the note (``[key]``)."""
        return [k for k in SOURCES if f"[{k}]" in self.note]


# Kelvin-Voigt viscosities: eta = tan(delta) E / omega, omega = 2 pi 45 kHz (the seed drive), i.e.
# the dashpot gives the loss tangent tan(delta) at the drive frequency. Illustrative (see
# docs/materials.md).
_OMEGA_SEED = 2.0 * math.pi * 45e3

_TABLE = (
    Material(
        "seed",
        70e6,
        0.3,
        6.4e-20,
        6.4e-20,
        0.0,
        "[seed] the seed notebook's DMT sample: conservative (eta 0, H_retract = H)",
    ),
    Material(
        "polystyrene",
        3.0e9,
        0.34,
        6.5e-20,
        1.3e-19,
        round(0.01 * 3.0e9 / _OMEGA_SEED, 1),
        "PS-like. E, nu: [polymer_handbook] (3.0-3.5 GPa, 0.33-0.35). H: [israelachvili] "
        "[walstra] "
        "6.5e-20 J. H_retract = 2 H: [illustrative] [dforce] (hysteresis factor; no tabulated "
        "value). "
        "eta = tan(delta) E / omega with tan(delta) = 0.01 (glassy PS at room temperature, "
        "typically "
        "~0.01-0.03) at 45 kHz: [illustrative] [kelvin_voigt]",
    ),
    Material(
        "ldpe",
        0.2e9,
        0.45,
        7.1e-20,
        1.42e-19,
        round(0.1 * 0.2e9 / _OMEGA_SEED, 1),
        "LDPE-like. E, nu: [polymer_handbook] (0.1-0.3 GPa: 0.2 GPa [illustrative]; nu "
        "0.45-0.49). "
        "H: solid paraffin 7.1e-20 J as the closest tabulated saturated hydrocarbon [walstra] "
        "(hydrocarbons 5-10e-20 J [israelachvili]). H_retract = 2 H: [illustrative] [dforce]. "
        "eta from tan(delta) = 0.1 (rubbery amorphous phase, typically ~0.05-0.2) at 45 kHz: "
        "[illustrative] [kelvin_voigt]",
    ),
    Material(
        "silicon",
        169e9,
        0.28,
        1.9e-19,
        1.9e-19,
        0.0,
        "crystalline Si (no oxide). E 169 GPa (<110>), nu 0.28: [hopcroft] (130-188 GPa, "
        "0.064-0.36). "
        "H: [illustrative] 1.9e-19 J, Lifshitz values for Si ~1.8-2.6e-19 J [bergstrom]. "
        "Elastic and non-hysteretic at this time scale: eta 0, H_retract = H",
    ),
    Material(
        "silicon_oxide",
        72e9,
        0.17,
        6.5e-20,
        6.5e-20,
        0.0,
        "amorphous SiO2 / native oxide. E, nu: [silica] (72-73 GPa, 0.16-0.17). H: 6.5e-20 J "
        "[israelachvili] [bergstrom] (fused quartz 6.3e-20, silica 6.5e-20). eta 0, H_retract = H",
    ),
    Material(
        "mica",
        60e9,
        0.25,
        1.0e-19,
        1.0e-19,
        0.0,
        "muscovite, loaded normal to the cleavage plane. E: c33 ~ 60 GPa [mica]; nu 0.25 "
        "[illustrative] (anisotropic: 0.1-0.35 by direction). H: 1.0e-19 J [israelachvili] "
        "(Lifshitz ~1e-19, measured up to 1.35e-19 J). eta 0, H_retract = H",
    ),
)

MATERIALS: dict[str, Material] = {m.name: m for m in _TABLE}


def material(name: str) -> Material:
    """The named material; ValueError naming ``material`` and the allowed names for an unknown
    one."""
    if isinstance(name, Material):
        return name
    try:
        return MATERIALS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"material={name!r} is not known; allowed: {', '.join(repr(n) for n in MATERIALS)}"
        ) from None


_SAMPLE_FIELDS = set(DMT_SPECS)
_EXTRA = {"viscosity", "hamaker_constant_retract"}


def sample_for(mat, tip: Material | None = None, **overrides):
    """(DMTSample, viscosity [Pa s], hamaker_retract [J]) for material ``mat`` (a name or a
    Material).

    The sample takes E, nu and H from the material, the tip radius, a0 and the tip's E and nu from
    the DMT_SPECS defaults (a silicon tip, 130 GPa, 0.3). With ``tip`` a Material, its E and nu are
    the tip's and the Hamaker constants combine as sqrt(H_tip H_sample) (Israelachvili's combining
    relation). Keyword ``overrides`` (any DMTSample field, ``viscosity``,
    ``hamaker_constant_retract``) win over the material's values.
    """
    m = material(mat)
    unknown = set(overrides) - _SAMPLE_FIELDS - _EXTRA
    if unknown:
        raise ValueError(
            f"unknown override(s) {sorted(unknown)}; allowed: "
            f"{', '.join(sorted(_SAMPLE_FIELDS | _EXTRA))}"
        )
    h, h_r = m.hamaker_constant, m.hamaker_constant_retract
    fields = {"sample_youngs_modulus": m.youngs_modulus, "sample_poisson_ratio": m.poisson_ratio}
    if tip is not None:
        tip = material(tip)
        fields["tip_youngs_modulus"] = tip.youngs_modulus
        fields["tip_poisson_ratio"] = tip.poisson_ratio
        h = math.sqrt(tip.hamaker_constant * h)
        h_r = math.sqrt(tip.hamaker_constant_retract * h_r)
    fields["hamaker_constant"] = h
    fields.update({k: v for k, v in overrides.items() if k in _SAMPLE_FIELDS})
    viscosity = overrides.get("viscosity", m.viscosity)
    h_r = overrides.get("hamaker_constant_retract", h_r)
    # validate the extras through a Material (same rules as the table)
    checked = replace(m, viscosity=viscosity, hamaker_constant_retract=h_r)
    return DMTSample(**fields), checked.viscosity, checked.hamaker_constant_retract
