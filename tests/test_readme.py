"""The README's API example runs as written and prints what the README says it prints
(documentation that cannot rot)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _numbers(text: str) -> list[str]:
    return re.findall(r"[−+-]?\d+\.\d+", text.replace("−", "-"))


@pytest.mark.slow
def test_readme_api_example_prints_what_the_readme_says(tmp_path):
    """Run the Python block in a fresh interpreter; the numbers of the sentence "It
    prints …" after it are the ones it printed, in order, to their last digit."""
    text = README.read_text()
    block = re.search(r"```python\n(.*?)```", text, flags=re.S).group(1)
    said = re.search(r"```python\n.*?```\n\nIt prints (.*?)\.\s", text, flags=re.S).group(1)
    r = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    printed = r.stdout.splitlines()
    assert len(printed) == 3 and all(":" in line for line in printed), r.stdout
    # the quoted values, to their last digit (another CPU count may round differently)
    quoted = [float(x) for x in _numbers(said)]
    got = [float(_numbers(line)[-1]) for line in printed]
    assert quoted == pytest.approx(got, abs=1.5e-3), (quoted, got)
