"""File formats of afm_ros (no ROS): Gwyddion ``.gwy`` images (:mod:`afm_ros.formats.gwy`)."""
