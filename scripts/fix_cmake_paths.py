"""Rewrite the build-container paths baked into the ROS 2 wheels' exported CMake files.

The PyPI wheels were built in a manylinux container whose Python lived in
``/opt/python/cpXY-cpXY``; their exported CMake targets name that interpreter's include
directory and numpy include directory, which do not exist here, so ``colcon build`` of
any interface package fails. Point them at this interpreter and this venv. Idempotent.
"""
from __future__ import annotations

import re
import sys
import sysconfig
from pathlib import Path

CONTAINER = re.compile(r"/opt/python/cp3\d+-cp3\d+")


def rewrite(prefix: Path) -> int:
    include = sysconfig.get_paths()["include"]
    site = sysconfig.get_paths()["purelib"]
    pyver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    subs = [
        (re.compile(CONTAINER.pattern + r"/include/python3\.\d+"), include),
        (re.compile(CONTAINER.pattern + r"/lib/python3\.\d+/site-packages"), site),
        (CONTAINER, str(prefix)),
    ]
    changed = 0
    for path in (prefix / "share").rglob("*"):
        if not path.is_file() or path.suffix in {".so", ".a", ".pyc", ".png"}:
            continue
        try:
            text = path.read_text()
        except (UnicodeDecodeError, OSError):
            continue
        if "/opt/python/cp3" not in text:
            continue
        for pattern, repl in subs:
            text = pattern.sub(repl.replace("\\", "\\\\"), text)
        path.write_text(text)
        changed += 1
    numpy_inc = Path(site) / "numpy" / "_core" / "include"
    if not numpy_inc.is_dir():
        print(f"warning: numpy include dir {numpy_inc} not found", file=sys.stderr)
    print(f"fix_cmake_paths: rewrote {changed} files under {prefix}/share for {pyver}")
    return changed


if __name__ == "__main__":
    rewrite(Path(sys.argv[1] if len(sys.argv) > 1 else sys.prefix).resolve())
