"""``python -m afm_ros.tools.config_gen yaml|table``: print ``config/afm.yaml`` or the Markdown
parameter table (docs/parameters.md) generated from the parameter specs
(:mod:`afm_ros.core.specs`). A test checks that the committed files agree with the specs.
"""

from __future__ import annotations

import argparse
import sys

from afm_ros.core.specs import table_text, yaml_text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.config_gen", description=__doc__
    )
    parser.add_argument("what", choices=["yaml", "table"])
    args = parser.parse_args(argv)
    sys.stdout.write(yaml_text() if args.what == "yaml" else table_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
