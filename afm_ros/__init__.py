"""afm_ros: a ROS 2 Jazzy emulator of a tapping-mode atomic force microscope."""

__version__ = "0.1.0"

# Before any afm_ros module imports numba: a writable place for the compiled kernels, also when
# the package itself is installed read-only (see afm_ros/numba_cache.py).
from afm_ros import ament_env as _ament_env
from afm_ros import numba_cache as _numba_cache

_numba_cache.configure()
# message definitions of the PyPI ROS wheels live under sys.prefix (see afm_ros/ament_env.py)
_ament_env.configure()
