"""config/afm.yaml and the README parameter table agree with the parameter specs (one source)."""
from pathlib import Path

import pytest
import yaml

from afm_ros.config_gen import node_specs, table_text

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def config():
    return yaml.safe_load((ROOT / "config" / "afm.yaml").read_text())


def test_every_node_has_specs():
    # the five instrument blocks each declare their parameters through specs
    assert set(node_specs()) == {"cantilever", "lockin", "z_controller", "recorder", "replay"}


def test_yaml_holds_every_spec_default_and_validates(config):
    for node, specs in node_specs().items():
        params = config[node]["ros__parameters"]
        assert set(params) == set(specs), f"{node}: YAML and specs list different parameters"
        for name, spec in specs.items():
            assert spec.validate(params[name]) == spec.default, f"{node}.{name}"


def test_readme_table_matches_specs():
    readme = (ROOT / "README.md").read_text()
    for row in table_text().splitlines()[2:]:
        assert row in readme, f"README parameter table is missing or stale: {row}"
