#!/usr/bin/env bash
# Run a command inside the suite's environment (venv, ROS, workspace), with our own DDS
# settings whatever the shell exported: loopback only, a private domain (LQ_ISOLATED in env.sh).
set -eo pipefail
LQ_ISOLATED=1
source "$(dirname "$0")/env.sh"
cd "$LQ_ROOT"
exec "$@"
