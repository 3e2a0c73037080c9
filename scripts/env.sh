# Source this file (bash): selects the ROS 2 Jazzy installation, activates .venv, sources the
# built workspace, puts its executables on PATH and fills in the DDS settings you have not set.
#   /opt/ros/jazzy present -> that installation (system mode); else the PyPI wheels in .venv.
#   LQ_ROS_MODE=wheels forces the wheels even when /opt/ros/jazzy exists.
#
# DDS settings. A shell that sources this file keeps every ROS_DOMAIN_ID, RMW_IMPLEMENTATION,
# ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_LOCALHOST_ONLY, ROS_STATIC_PEERS and
# FASTRTPS_DEFAULT_PROFILES_FILE it already exported, and gets only the missing ones:
#   ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (unless ROS_LOCALHOST_ONLY / ROS_STATIC_PEERS say
#   otherwise), RMW_IMPLEMENTATION=rmw_fastrtps_cpp, ROS_DOMAIN_ID=$LQ_ROS_DOMAIN_ID if that is
#   set (else ROS's default, 0, shared with your other terminals), and our Fast DDS profile
#   (config/fastdds_loopback_shm.xml: shared memory + UDP on 127.0.0.1 only; with a
#   discovery range beyond this host, the same shared memory + UDP on every interface).
#   LQ_SHM_SEGMENT_MB=N sizes the profile's shared-memory segment in MiB (default 64): the
#   largest message that survives a briefly busy receiver. Another size than 64 is written to
#   ${XDG_CACHE_HOME:-~/.cache}/lidar_quality/ (or $LQ_PROFILE_DIR) and used from there.
# Our own scripts, tests and CI set LQ_ISOLATED=1 (with_env.sh, run_tests.sh, build_ws.sh):
# then whatever the shell had, DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
# no static peers, Fast DDS with the loopback profile) in a private domain: LQ_ROS_DOMAIN_ID,
# else one leased with the file locks of lidar_quality_ros/domain.py and held until the
# command ends, so tests never lease it too.
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

# --- DDS ------------------------------------------------------------------------------------
_lq_default_mb=64  # = config/fastdds_loopback_shm.xml
_lq_mb="${LQ_SHM_SEGMENT_MB:-$_lq_default_mb}"
case "$_lq_mb" in
  ''|*[!0-9]*|0*) _lq_ok=0 ;;
  *) if [ "${#_lq_mb}" -le 4 ] && [ "$_lq_mb" -le 4095 ]; then _lq_ok=1; else _lq_ok=0; fi ;;
esac
if [ "$_lq_ok" = 0 ]; then
  echo "env.sh: LQ_SHM_SEGMENT_MB=$_lq_mb is not a whole number of MiB in 1..4095" \
       "(Fast DDS segments are below 4 GiB); using $_lq_default_mb" >&2
  _lq_mb=$_lq_default_mb
fi

# Path of the Fast DDS profile with a segment of $1 MiB, $2 = loopback | network; written from
# the shipped profile (the one source of truth) when it is not the shipped one itself.
_lq_profile() {
  local src="$LQ_ROOT/config/fastdds_loopback_shm.xml" dir out tmp
  local -a edits
  if [ "$1" = "$_lq_default_mb" ] && [ "$2" = loopback ]; then echo "$src"; return 0; fi
  dir="${LQ_PROFILE_DIR:-}"
  if [ -z "$dir" ] && { [ -n "${XDG_CACHE_HOME:-}" ] || [ -d "${HOME:-}" ]; }; then
    dir="${XDG_CACHE_HOME:-$HOME/.cache}/lidar_quality"
  fi
  if [ -z "$dir" ] || ! mkdir -p "$dir" 2>/dev/null || [ ! -w "$dir" ]; then
    dir="${TMPDIR:-/tmp}/lidar_quality-$(id -u)"; mkdir -p "$dir" || return 1
  fi
  out="$dir/fastdds_${2}_shm_${1}mib.xml"
  tmp="$out.$$.tmp"
  # One queue slot per <= 64 KiB fragment of a full segment, twice over: the queue must never
  # be the smaller limit (Fast DDS's default, 512 slots, capped clouds at 33.5 MB).
  edits=(-e "s|<segment_size>[0-9]*</segment_size>|<segment_size>$(( $1 * 1048576 ))</segment_size>|"
         -e "s|<port_queue_capacity>[0-9]*</port_queue_capacity>|<port_queue_capacity>$(( $1 * 32 ))</port_queue_capacity>|"
         -e "1a <!-- Written by scripts/env.sh from config/fastdds_loopback_shm.xml: LQ_SHM_SEGMENT_MB=$1, $2. -->")
  # network: UDP on every interface, for a discovery range beyond this host
  if [ "$2" = network ]; then
    edits+=(-e '/<interfaceWhiteList>/,/<\/interfaceWhiteList>/d' -e 's/lq_udp_loopback/lq_udp/g')
  fi
  if sed "${edits[@]}" "$src" > "$tmp" && mv -f "$tmp" "$out"; then echo "$out"; return 0; fi
  rm -f "$tmp"
  return 1
}

# Take the lock of domain $1 in the lock directory of lidar_quality_ros/domain.py on a shell fd
# (inherited by the command, so held until it ends). Fails when another run holds it.
_lq_lock_domain() {
  local dir="${LQ_DOMAIN_LOCK_DIR:-${TMPDIR:-/tmp}/lidar_quality_domains}" f fd
  command -v flock >/dev/null || return 1
  mkdir -p "$dir" 2>/dev/null || return 1
  f="$dir/$1.lock"
  [ -e "$f" ] || (umask 0; : >> "$f") 2>/dev/null
  { exec {fd}<"$f"; } 2>/dev/null || return 1  # (a bare exec's 2>/dev/null would stay)
  if flock -n "$fd"; then LQ_DOMAIN_LOCK_FD=$fd; return 0; fi
  exec {fd}<&-
  return 1
}

if [ "${LQ_ISOLATED:-}" = 1 ]; then
  export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
  unset ROS_LOCALHOST_ONLY ROS_STATIC_PEERS
  export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
  if [ -n "${LQ_DOMAIN_LOCK_FD:-}" ]; then { exec {LQ_DOMAIN_LOCK_FD}<&-; } 2>/dev/null; fi
  unset LQ_DOMAIN_LOCK_FD
  if [ -n "${LQ_ROS_DOMAIN_ID:-}" ]; then
    ROS_DOMAIN_ID=$LQ_ROS_DOMAIN_ID
    _lq_lock_domain "$ROS_DOMAIN_ID" || true  # pinned: used even when someone else holds it
  else
    # Same order as DomainLease.acquire: domains 1..101, from this shell's PID on.
    ROS_DOMAIN_ID=$(( $$ % 101 + 1 ))
    for ((_lq_i = 0; _lq_i <= 100; _lq_i++)); do
      if _lq_lock_domain $(( ($$ + _lq_i) % 101 + 1 )); then
        ROS_DOMAIN_ID=$(( ($$ + _lq_i) % 101 + 1 )); break
      fi
    done
  fi
  export ROS_DOMAIN_ID
  _lq_p=$(_lq_profile "$_lq_mb" loopback) || _lq_p="$LQ_ROOT/config/fastdds_loopback_shm.xml"
  export FASTRTPS_DEFAULT_PROFILES_FILE="$_lq_p"
else
  if [ -z "${ROS_AUTOMATIC_DISCOVERY_RANGE:-}" ] && [ "${ROS_LOCALHOST_ONLY:-}" != 0 ] \
     && [ -z "${ROS_STATIC_PEERS:-}" ]; then
    export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
  fi
  if [ -z "${ROS_DOMAIN_ID:-}" ] && [ -n "${LQ_ROS_DOMAIN_ID:-}" ]; then
    export ROS_DOMAIN_ID="$LQ_ROS_DOMAIN_ID"
  fi
  export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
  # A profile this file chose before (sourced again) is ours to replace; any other is yours.
  if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ] \
     || [ "$FASTRTPS_DEFAULT_PROFILES_FILE" = "${LQ_PROFILE_FROM_ENV_SH:-}" ]; then
    if [ "${ROS_LOCALHOST_ONLY:-}" = 1 ] || { [ "${ROS_AUTOMATIC_DISCOVERY_RANGE:-}" = LOCALHOST ] \
         && [ -z "${ROS_STATIC_PEERS:-}" ]; }; then
      _lq_p=$(_lq_profile "$_lq_mb" loopback) || _lq_p=""
    else
      _lq_p=$(_lq_profile "$_lq_mb" network) || _lq_p=""
    fi
    if [ -n "$_lq_p" ]; then
      export FASTRTPS_DEFAULT_PROFILES_FILE="$_lq_p" LQ_PROFILE_FROM_ENV_SH="$_lq_p"
    fi
  elif [ -n "${LQ_SHM_SEGMENT_MB:-}" ]; then
    echo "env.sh: LQ_SHM_SEGMENT_MB ignored: FASTRTPS_DEFAULT_PROFILES_FILE is your own" \
         "($FASTRTPS_DEFAULT_PROFILES_FILE); set the segment there" >&2
  fi
fi
unset -f _lq_profile _lq_lock_domain
unset _lq_default_mb _lq_mb _lq_ok _lq_p _lq_i

if [ -f "$LQ_ROOT/ros2_ws/install/setup.bash" ]; then
  # shellcheck disable=SC1091
  source "$LQ_ROOT/ros2_ws/install/setup.bash"
  # ament_python installs console scripts into <prefix>/lib/<package> (for `ros2 run`, which
  # the wheels lack): put them on PATH so that `lmd-train`, `bag_player`, `lmd_node`, ... run.
  for _lq_d in "$LQ_ROOT"/ros2_ws/install/*/; do
    _lq_d="${_lq_d%/}/lib/$(basename "$_lq_d")"
    [ -d "$_lq_d" ] || continue
    case ":$PATH:" in *":$_lq_d:"*) ;; *) PATH="$_lq_d:$PATH" ;; esac
  done
  export PATH
  unset _lq_d
fi
