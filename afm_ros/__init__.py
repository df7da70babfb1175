"""afm_ros: a ROS 2 Jazzy emulator of a tapping-mode atomic force microscope."""
__version__ = "0.1.0"
