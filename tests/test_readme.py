"""The Python examples of the README and of the developer's guide run as written."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "docs" / "guide.md"]
BLOCKS = [
    (page.relative_to(ROOT).as_posix(), i, block)
    for page in PAGES
    for i, block in enumerate(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))
]


def test_pages_have_examples():
    assert sum(name == "README.md" for name, _, _ in BLOCKS) >= 2
    assert sum(name == "docs/guide.md" for name, _, _ in BLOCKS) >= 3


@pytest.mark.parametrize("name, index, block", BLOCKS, ids=[f"{n}[{i}]" for n, i, _ in BLOCKS])
def test_example_runs(name, index, block):
    exec(compile(block, f"{name}[python block {index}]", "exec"), {})
