# Source this file (bash): selects the ROS 2 Jazzy installation, activates .venv, keeps
# DDS on loopback and sources the built workspace when present.
#   /opt/ros/jazzy present -> that installation (system mode); else the PyPI wheels in .venv.
#   LQ_ROS_MODE=wheels forces the wheels even when /opt/ros/jazzy exists.
#   LQ_ROS_DOMAIN_ID=N pins the domain (default: one derived from this shell's PID).
LQ_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export LQ_ROOT
if [ -z "${LQ_ROS_MODE:-}" ]; then
  if [ -f /opt/ros/jazzy/setup.bash ]; then LQ_ROS_MODE=system; else LQ_ROS_MODE=wheels; fi
fi
export LQ_ROS_MODE
if [ "$LQ_ROS_MODE" = system ]; then
  # shellcheck disable=SC1091
  source /opt/ros/jazzy/setup.bash
fi
if [ -f "$LQ_ROOT/.venv/bin/activate" ]; then
  # shellcheck disable=SC1091
  source "$LQ_ROOT/.venv/bin/activate"
  if [ "$LQ_ROS_MODE" = wheels ]; then
    # The wheels install an ament prefix (share/, lib/) into the venv itself.
    case ":${AMENT_PREFIX_PATH:-}:" in *":$VIRTUAL_ENV:"*) ;; *)
      export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;; esac
    case ":${CMAKE_PREFIX_PATH:-}:" in *":$VIRTUAL_ENV:"*) ;; *)
      export CMAKE_PREFIX_PATH="$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}" ;; esac
  fi
fi
# Network rule: DDS discovery and traffic stay on this host, in a run-specific domain.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${LQ_ROS_DOMAIN_ID:-$(( $$ % 100 + 1 ))}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$LQ_ROOT/config/fastdds_loopback_shm.xml}"
if [ -f "$LQ_ROOT/ros2_ws/install/setup.bash" ]; then
  # shellcheck disable=SC1091
  source "$LQ_ROOT/ros2_ws/install/setup.bash"
fi
