"""Code printed in the docs, extracted so tests run exactly what a user copies."""

import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _block(doc: str, marker: str, language: str) -> str:
    """The fenced code block right after `<!-- marker -->` in docs/`doc`."""
    text = (DOCS / doc).read_text()
    m = re.search(rf"<!-- {marker} -->\n```{language}\n(.*?)```", text, re.S)
    assert m, f"docs/{doc} lost its {marker} block"
    return m.group(1)


def adapter_example() -> str:
    """The minimal camera adapter of docs/camera-protocol.md (the block after its marker)."""
    return _block("camera-protocol.md", "adapter-example", "python")


def tls_recipe() -> tuple[str, str]:
    """The openssl commands of docs/sharing.md making a swarm CA, and a certificate for drone 3."""
    return _block("sharing.md", "tls-ca", "sh"), _block("sharing.md", "tls-drone", "sh")
