"""Virtual samples (numpy + numba, no ROS): height and material maps, generators, tip dilation.

See ``docs/samples.md``. A sample repeats periodically outside its map.
"""

from afm_ros.core.samples.description import (
    builtin_samples,
    describe,
    load_sample_file,
    resolve_sample,
    sample_from_description,
)
from afm_ros.core.samples.generators import (
    GENERATORS,
    SPECS,
    blend,
    from_file,
    grating,
    rough,
    terraces,
)
from afm_ros.core.samples.surface import Sample, dilate, surface_at

__all__ = [
    "Sample",
    "surface_at",
    "dilate",
    "grating",
    "blend",
    "terraces",
    "rough",
    "from_file",
    "GENERATORS",
    "SPECS",
    "sample_from_description",
    "load_sample_file",
    "describe",
    "builtin_samples",
    "resolve_sample",
]
