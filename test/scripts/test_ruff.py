"""ruff (ruff.toml) passes on the repository, and every ``# noqa`` says why it is there."""
import io
import re
import subprocess
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUFF = Path(sys.executable).parent / "ruff"  # the venv's, installed from requirements/
NOQA = re.compile(r"#\s*noqa\b", re.IGNORECASE)
# "# noqa: E402 - bench/ goes on sys.path first": codes, then " - " and the reason.
NOQA_WITH_REASON = re.compile(r"#\s*noqa:\s*[A-Z]+[0-9]+(\s*,\s*[A-Z]+[0-9]+)*\s+-\s+\S")


def ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(RUFF), *args, "--no-cache", "."], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def noqa_without_reason(source: str) -> list[int]:
    """Line numbers of the ``noqa`` comments in ``source`` that name no code or give no reason."""
    lines = []
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT and NOQA.search(tok.string):
            if not NOQA_WITH_REASON.search(tok.string):
                lines.append(tok.start[0])
    return lines


def test_ruff_passes():
    out = ruff("check", "--output-format", "concise")
    assert out.returncode == 0, out.stdout + out.stderr


def test_every_noqa_has_a_reason():
    files = ruff("check", "--show-files").stdout.splitlines()
    py = [Path(f) for f in files if f.endswith(".py")]
    assert len(py) > 100 and not any("ros2_ws" in p.parts or ".venv" in p.parts for p in py)
    bare = [f"{p.relative_to(ROOT)}:{n}" for p in py for n in noqa_without_reason(p.read_text())]
    assert not bare, "# noqa without '<CODE> - <reason>': " + ", ".join(bare)


def test_reason_check_catches_bare_markers():
    src = ("import os  # noqa: F401 - re-exported\n"
           "import sys  # noqa: F401\n"
           "x = 1  # noqa\n"
           "y = 2  # NOQA - no code\n"
           "s = '# noqa'  # a string, not a marker\n")
    assert noqa_without_reason(src) == [2, 3, 4]


def test_pinned_version_is_the_installed_one():
    pins = {f: re.search(r"^ruff==(\S+)", (ROOT / "requirements" / f).read_text(), re.M)
            for f in ("python.in", "lock-wheels.txt")}
    assert all(pins.values()), pins
    installed = subprocess.run([str(RUFF), "--version"], capture_output=True, text=True).stdout.split()[-1]
    assert {m.group(1) for m in pins.values()} == {installed}
