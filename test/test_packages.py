"""Package boundaries: every import of a ROS package (ours or not), including the ones
inside functions, is declared in the importing package's package.xml; no dependency
cycle; node packages import no other node package; runtime packages import neither the
simulator, the reference perception nor the offline tools."""
import ast
import re
from pathlib import Path

import pytest
from ament_index_python.packages import get_packages_with_prefixes

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in ROOT.glob("*/package.xml"))
NODE_PACKAGES = {"lmd_ros", "lms_ros", "mimo_ros"}
RUNTIME = NODE_PACKAGES | {"lidar_quality_core", "lidar_quality_ros"}
OFFLINE = {"lidar_sim", "reference_perception", "lidar_quality_training", "lidar_quality_tools"}


def declared(pkg: str) -> set[str]:
    xml = (ROOT / pkg / "package.xml").read_text()
    return set(re.findall(r"<(?:exec_|build_|build_export_|)depend>\s*([\w]+)\s*</", xml))


def imported(pkg: str) -> dict[str, set[str]]:
    """Top-level modules imported anywhere in ``pkg``'s Python package -> files."""
    out: dict[str, set[str]] = {}
    for f in sorted((ROOT / pkg / pkg).rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                out.setdefault(name.split(".")[0], set()).add(str(f.relative_to(ROOT)))
    return out


ROS_PACKAGES = set(get_packages_with_prefixes()) | set(PACKAGES)


def test_the_parse_sees_imports_inside_functions():
    # mimo_ros.pipeline imports the cloud decoder inside a function
    assert "lidar_quality_core" in imported("mimo_ros")
    assert {"lmd_ros", "lms_ros", "mimo_ros", "lidar_quality_training"} <= set(PACKAGES)


@pytest.mark.parametrize("pkg", PACKAGES)
def test_every_ros_import_is_declared(pkg):
    missing = {m: sorted(f) for m, f in imported(pkg).items()
               if m in ROS_PACKAGES and m != pkg and m not in declared(pkg)}
    assert not missing, f"{pkg}/package.xml does not declare: {missing}"


def test_no_dependency_cycle():
    graph = {p: declared(p) & set(PACKAGES) for p in PACKAGES}
    done, path = set(), []

    def visit(p):
        if p in path:
            raise AssertionError("dependency cycle: " + " -> ".join(path[path.index(p):] + [p]))
        if p in done:
            return
        path.append(p)
        for q in sorted(graph[p]):
            visit(q)
        path.pop()
        done.add(p)

    for p in PACKAGES:
        visit(p)


@pytest.mark.parametrize("pkg", sorted(RUNTIME))
def test_runtime_packages_stay_runtime(pkg):
    mods = imported(pkg)
    offline = {m: sorted(mods[m]) for m in OFFLINE if m in mods}
    assert not offline, f"{pkg} imports offline packages: {offline}"
    if pkg in NODE_PACKAGES:
        others = {m: sorted(mods[m]) for m in NODE_PACKAGES - {pkg} if m in mods}
        assert not others, f"{pkg} imports other node packages: {others}"
