"""``python -m afm_ros.tools.report``: the ``afm_report`` command."""

import sys

from afm_ros.tools.report import main

sys.exit(main())
