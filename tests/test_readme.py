"""README.md's Python blocks run as tests (pytest-markdown-docs, configured in pyproject.toml):
this keeps that wiring from being dropped and lets only hardware blocks opt out."""

import re
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_blocks_are_collected_by_the_suite():
    opts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert "README.md" in opts["testpaths"] and "--markdown-docs" in opts["addopts"]
    readme = (ROOT / "README.md").read_text()
    fences = re.findall(r"^```python([^\n]*)\n(.*?)^```", readme, flags=re.M | re.S)
    assert len(fences) >= 3
    for flags, body in fences:
        if "notest" in flags:  # only code that needs real DWM1001 devices may opt out
            assert "/dev/tty" in body, body[:80]


def test_readme_test_command_is_one_line_with_the_client_extra():
    block = re.search(r"<!-- test-command -->\n```\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    lines = block.group(1).strip().splitlines()
    assert len(lines) == 1 and "clients" in lines[0] and "pytest" in lines[0]
