"""Code printed in the docs, extracted so tests run exactly what a user copies."""

import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def adapter_example() -> str:
    """The minimal camera adapter of docs/camera-protocol.md (the block after its marker)."""
    text = (DOCS / "camera-protocol.md").read_text()
    m = re.search(r"<!-- adapter-example -->\n```python\n(.*?)```", text, re.S)
    assert m, "docs/camera-protocol.md lost its adapter example"
    return m.group(1)
