"""Tests that prove a promise the README makes (the systemd boot, the multi-host swarm in network
namespaces) may skip on a developer's laptop, never silently in CI: run as root with CI=true, a
proof that cannot run fails instead of skipping."""

import os

import pytest


def in_ci_as_root() -> bool:
    return os.environ.get("CI") == "true" and os.geteuid() == 0


def skip_proof(reason: str) -> None:
    """pytest.skip(reason), or pytest.fail in CI as root: the proof must run there."""
    if in_ci_as_root():
        pytest.fail(f"a proof could not run in CI as root: {reason}", pytrace=False)
    pytest.skip(reason)
