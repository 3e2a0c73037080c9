"""scripts/build_ws.sh builds our vision_msgs copy only when no vision_msgs is installed."""
import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _which(ament_prefix_path: str) -> str:
    env = dict(os.environ, AMENT_PREFIX_PATH=ament_prefix_path)
    out = subprocess.run(["bash", str(ROOT / "scripts" / "build_ws.sh"), "--which-vision-msgs"],
                         env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_installed_vision_msgs_is_used(tmp_path):
    prefix = tmp_path / "opt_ros_jazzy"
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages"
    marker.mkdir(parents=True)
    (marker / "vision_msgs").touch()
    assert _which(f"{prefix}:{os.environ.get('AMENT_PREFIX_PATH', '')}") == str(prefix)


def test_own_copy_built_when_absent(tmp_path):
    # Our own install of the copy must not count as "installed".
    assert _which(os.environ.get("AMENT_PREFIX_PATH", "")) == "build"


def test_workspace_has_no_shadowing_copy_here():
    ignore = ROOT / "ros2_ws" / "src" / "vision_msgs" / "COLCON_IGNORE"
    assert ignore.exists() == (_which(os.environ.get("AMENT_PREFIX_PATH", "")) != "build")
