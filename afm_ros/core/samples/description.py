"""Sample descriptions: a dict (or a YAML / JSON file) naming a generator and its parameters.

    generator: blend            # grating, blend, terraces, rough or from_file
    matrix: polystyrene         # material names: afm_ros.core.physics.materials.MATERIALS
    islands: ldpe
    island_fraction: 0.3
    size: [10.0e-6, 10.0e-6]    # [m]; SI units throughout
    tip_radius: 20.0e-9         # optional: the tip-dilated surface (what the apex follows)

Missing parameters take the generator's defaults; :func:`describe` gives the complete dict.
"""

from __future__ import annotations

import copy
import os
import sys

from afm_ros.core.physics.parameters import DMT_SPECS, parse_number
from afm_ros.core.samples.generators import GENERATORS, MAP_EXTENSIONS, PAIRS, SPECS, from_file
from afm_ros.core.samples.surface import Sample, dilate
from afm_ros.formats import user_files

TOP_LEVEL = ("generator", "tip_radius")


def _numbers_from_text(spec, value):
    """YAML 1.1 reads ``20e-9`` (no dot) as a string: numeric fields accept numeric text."""
    if spec.kind in (int, float) and isinstance(value, str):
        return parse_number(value)
    return value


def sample_from_description(description: dict, base_dir: str | None = None) -> Sample:
    """The sample of ``description`` (see the module doc); a relative ``from_file`` path is taken
    relative to ``base_dir`` (default the working directory)."""
    if not isinstance(description, dict):
        raise ValueError(
            f"a sample description must be a mapping, got {type(description).__name__}"
        )
    generator = description.get("generator")
    if generator not in GENERATORS:
        raise ValueError(
            f"generator={generator!r} is not known; allowed: "
            f"{', '.join(repr(g) for g in GENERATORS)}"
        )
    specs = SPECS[generator]
    unknown = [k for k in description if k not in specs and k not in TOP_LEVEL]
    if unknown:
        raise ValueError(
            f"unknown key(s) {', '.join(repr(k) for k in unknown)} for generator {generator!r}; "
            f"allowed: {', '.join(repr(k) for k in (*TOP_LEVEL, *specs))}"
        )
    kwargs = {}
    for name, value in description.items():
        if name in TOP_LEVEL:
            continue
        spec = specs[name]
        if name in PAIRS and isinstance(value, (list, tuple)):
            value = [_numbers_from_text(spec, v) for v in value]
        else:
            value = _numbers_from_text(spec, value)
        kwargs[name] = value
    if generator == "from_file" and isinstance(kwargs.get("path"), str) and base_dir is not None:
        kwargs["path"] = os.path.join(base_dir, os.path.expanduser(kwargs["path"]))
    sample = GENERATORS[generator](**kwargs)
    if description.get("tip_radius") is not None:
        radius = DMT_SPECS["tip_radius"].validate(
            _numbers_from_text(DMT_SPECS["tip_radius"], description["tip_radius"])
        )
        sample = dilate(sample, radius)
    return sample


def load_sample_file(path) -> Sample:
    """The sample described by a YAML (``.yaml``/``.yml``) or JSON (``.json``) file.

    Errors name the file: OSError if it cannot be read, ValueError for its contents.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise OSError(2, f"cannot read sample description {path}: No such file or directory")
    data = user_files.load(path, "sample description")  # bounded: size, depth, aliases; ValueError
    try:
        return sample_from_description(data, base_dir=os.path.dirname(os.path.abspath(path)))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def describe(sample: Sample) -> dict:
    """The description that rebuilds ``sample`` (generator, every parameter, tip_radius if
    dilated)."""
    if not sample.description:
        raise ValueError(
            "the sample has no description (it was not made by a generator); "
            "build it with a generator or sample_from_description"
        )
    return copy.deepcopy(sample.description)


def builtin_sample_dirs() -> list[str]:
    """Folders searched for named sample descriptions: the source tree's ``config/samples`` and the
    installed ``share/afm_ros/config/samples`` of this Python prefix."""

    here = os.path.dirname(os.path.abspath(__file__))
    source = os.path.normpath(os.path.join(here, "..", "..", "..", "config", "samples"))
    installed = os.path.join(sys.prefix, "share", "afm_ros", "config", "samples")
    return [d for d in dict.fromkeys([source, installed]) if os.path.isdir(d)]


def builtin_samples() -> dict[str, str]:
    """Named sample descriptions shipped with afm_ros: name -> file."""
    out = {}
    for folder in builtin_sample_dirs():
        for name in sorted(os.listdir(folder)):
            stem, ext = os.path.splitext(name)
            if ext in (".yaml", ".yml", ".json") and stem not in out:
                out[stem] = os.path.join(folder, name)
    return out


def resolve_sample(spec: str) -> Sample | None:
    """``''`` or ``'flat'``: None (the flat sample of the force parameters); a built-in name
    (:func:`builtin_samples`); a description file (``.yaml``, ``.yml``, ``.json``); or a height map
    file (``.gwy``: its first channel at the file's real size; ``.npy``/``.png`` need a size, so
    they come through a description file). Every sample parameter and ``--sample`` flag goes
    through here. Errors name the sample and the allowed names."""
    if not isinstance(spec, str):
        raise ValueError(
            f"sample={spec!r} must be a string: '', 'flat', a built-in name or a file"
        )
    if spec in ("", "flat"):
        return None
    named = builtin_samples()
    if spec in named:
        return load_sample_file(named[spec])
    ext = os.path.splitext(spec)[1].lower()
    if ext in (".yaml", ".yml", ".json", *MAP_EXTENSIONS) or os.sep in spec:
        if not os.path.exists(spec):
            raise ValueError(f"sample={spec!r}: no such file")
        if ext in MAP_EXTENSIONS:
            return from_file(spec)
        return load_sample_file(spec)
    raise ValueError(
        f"sample={spec!r} is not known; allowed: 'flat', "
        + ", ".join(repr(n) for n in named)
        + " or a sample description file (.yaml, .json) or a "
        ".gwy height map"
    )
