"""``python -m afm_ros.tools.config_gen yaml|table|nanonis|bimodal``: print ``config/afm.yaml``,
the Markdown parameter table (docs/parameters.md) generated from the parameter specs
(:mod:`afm_ros.core.specs`), the Nanonis command table (docs/nanonis.md) generated from the
server's command declarations (:mod:`afm_ros.client.nanonis`) or the bimodal session's table
(docs/bimodal.md). Tests check that the committed files agree with them.
"""

from __future__ import annotations

import argparse
import sys

from afm_ros.client.nanonis.commands import command_table
from afm_ros.client.nanonis.signals import signal_table
from afm_ros.core.bimodal_scan import BIMODAL_SPECS
from afm_ros.core.specs import session_table, table_text, yaml_text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.config_gen", description=__doc__
    )
    parser.add_argument("what", choices=["yaml", "table", "nanonis", "bimodal"])
    args = parser.parse_args(argv)
    text = {
        "yaml": yaml_text,
        "table": table_text,
        "nanonis": lambda: command_table() + "\n" + signal_table(),
        "bimodal": lambda: session_table(BIMODAL_SPECS),
    }[args.what]()
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
