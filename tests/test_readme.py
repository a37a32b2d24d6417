"""The README's API tour runs as written (documentation that cannot rot)."""

import re
from pathlib import Path

import pytest


@pytest.mark.slow
def test_readme_python_tour_runs():
    """Extract the README's Python block and execute it."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "the README has no Python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
