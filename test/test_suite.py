"""The suite's own rules (conftest.py): under ``pytest -n 2`` two test files run side by side, so
each file whose processes talk over localhost DDS has its own ROS_DOMAIN_ID, and the markers are
the declared ones."""

from __future__ import annotations

import configparser
import re
from pathlib import Path

from conftest import DOMAIN_IDS

TEST_DIR = Path(__file__).resolve().parent
# a domain id written as a literal: DOMAIN_ID = "73", "ROS_DOMAIN_ID": "31", ROS_DOMAIN_ID="41"
LITERAL = re.compile(r"""DOMAIN_ID['"]?\s*[:=]\s*['"]?(\d+)""")


def test_each_file_has_its_own_ros_domain():
    assert len(set(DOMAIN_IDS.values())) == len(DOMAIN_IDS), DOMAIN_IDS
    assert all(0 <= d <= 101 for d in DOMAIN_IDS.values()), DOMAIN_IDS
    assert all((TEST_DIR / f"{name}.py").is_file() for name in DOMAIN_IDS), DOMAIN_IDS
    for path in sorted(set(TEST_DIR.glob("test_*.py")) - {Path(__file__).resolve()}):
        for literal in LITERAL.findall(path.read_text()):
            assert DOMAIN_IDS.get(path.stem) == int(literal), (
                f"{path.name} uses ROS_DOMAIN_ID {literal}: take the file's own id from "
                "conftest.DOMAIN_IDS (domain_id(__name__))"
            )


def test_the_markers_are_declared_and_strict():
    cfg = configparser.ConfigParser()
    cfg.read(TEST_DIR.parent / "setup.cfg")
    pytest_cfg = cfg["tool:pytest"]
    assert "--strict-markers" in pytest_cfg["addopts"]
    declared = {line.split(":")[0].strip() for line in pytest_cfg["markers"].strip().splitlines()}
    assert declared == {"ros", "slow"}
