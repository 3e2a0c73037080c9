#!/usr/bin/env bash
# Run a command inside the suite's environment (venv, ROS, workspace, loopback-only DDS).
set -eo pipefail
source "$(dirname "$0")/env.sh"
cd "$LQ_ROOT"
exec "$@"
