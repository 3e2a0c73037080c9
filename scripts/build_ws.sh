#!/usr/bin/env bash
# colcon build of ros2_ws/. Our vision_msgs copy is built only when the environment has
# none: with an installed vision_msgs it is marked COLCON_IGNORE so it never shadows it.
# --which-vision-msgs only prints that decision (an install prefix, or "build").
set -eo pipefail
cd "$(dirname "$0")/.."
LQ_ISOLATED=1
source scripts/env.sh
ignore=ros2_ws/src/vision_msgs/COLCON_IGNORE
external=""
IFS=: read -ra prefixes <<< "${AMENT_PREFIX_PATH:-}"
for p in "${prefixes[@]}"; do
  case "$p" in "$LQ_ROOT/ros2_ws/install"*) continue ;; esac
  if [ -e "$p/share/ament_index/resource_index/packages/vision_msgs" ]; then external="$p"; break; fi
done
if [ "${1:-}" = --which-vision-msgs ]; then
  echo "${external:-build}"  # where vision_msgs would come from; changes nothing
  exit 0
fi
if [ -n "$external" ]; then
  echo "build: using the installed vision_msgs in $external"
  touch "$ignore"
else
  rm -f "$ignore"
fi
# the same rule for our other copies: tf2_msgs (TFMessage, TF2Error: no tf2_msgs wheel)
# and Autoware's detected-object messages
for pkg in tf2_msgs autoware_perception_msgs; do
  pkg_ignore=ros2_ws/src/$pkg/COLCON_IGNORE
  rm -f "$pkg_ignore"
  for p in "${prefixes[@]}"; do
    case "$p" in "$LQ_ROOT/ros2_ws/install"*) continue ;; esac
    if [ -e "$p/share/ament_index/resource_index/packages/$pkg" ]; then
      echo "build: using the installed $pkg in $p"; touch "$pkg_ignore"; break
    fi
  done
done
cd ros2_ws
colcon --log-base log build --symlink-install --event-handlers console_direct- \
  --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$(command -v python)" "$@"
cd "$LQ_ROOT"
# Compile the numba kernels of lidar_quality_core once, into their caches next to the
# modules (about 25 s on two cores): no node, test or benchmark pays it at start-up.
echo "build: compiling the numba kernels (cached)"
bash scripts/with_env.sh python -c "import lms_ros.pipeline, lmd_ros.pipeline, mimo_ros.pipeline"
