"""The shared core is importable without rclpy (offline training and evaluation use it)."""
import pkgutil
import subprocess
import sys

import lidar_quality_core


def test_no_module_imports_rclpy():
    modules = sorted(m.name for m in pkgutil.iter_modules(lidar_quality_core.__path__))
    assert {"pointcloud", "boxes", "time_sync", "model_store", "metrics"} <= set(modules)
    code = ("import importlib, sys\n"
            f"for m in {modules!r}: importlib.import_module('lidar_quality_core.' + m)\n"
            "bad = sorted(k for k in sys.modules if k.split('.')[0] in ('rclpy', 'rcl', 'rmw'))\n"
            "print(bad)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
