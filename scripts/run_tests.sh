#!/usr/bin/env bash
# The test suite (`make test`). Every test leases its own ROS domain; DDS stays on loopback.
set -eo pipefail
LQ_ISOLATED=1  # our own DDS settings whatever the shell exported (see env.sh)
source "$(dirname "$0")/env.sh"
cd "$LQ_ROOT"
echo "tests: ROS mode $LQ_ROS_MODE, ROS_DOMAIN_ID=$ROS_DOMAIN_ID, discovery $ROS_AUTOMATIC_DISCOVERY_RANGE"
# Lint first (ruff.toml; well under a second): a finding fails the run before any test.
ruff="$LQ_ROOT/.venv/bin/ruff"
[ -x "$ruff" ] || { echo "tests: $ruff is missing: run make setup" >&2; exit 1; }
"$ruff" check --quiet --no-cache . || { echo "tests: ruff found the problems above" >&2; exit 1; }
echo "tests: ruff passed"
exec python -m pytest "$@"
