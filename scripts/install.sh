#!/usr/bin/env bash
# Creates .venv beside this repository's files and installs afm_ros with everything it needs
# from PyPI (no ROS install required). Idempotent: a second run only checks.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  if ! "$python" -m venv .venv; then
    rm -rf .venv
    echo "install.sh: '$python -m venv' failed; on Debian install the venv module first:" >&2
    echo "  apt-get install -y python3-venv" >&2
    exit 1
  fi
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -r requirements.txt
.venv/bin/python -m pip install -q --no-deps -e .
# ament_index (used by rclpy tooling and by our config lookup) must see the venv prefix
.venv/bin/python - <<'PY'
import sys, pathlib
site = next(p for p in map(pathlib.Path, sys.path) if p.name == "site-packages")
(site / "afm_ros_ament.pth").write_text(
    "import os, sys; os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join("
    "dict.fromkeys([sys.prefix] + [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]))\n")
PY
echo "afm_ros installed in $root/.venv"
