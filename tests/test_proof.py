"""A proof that cannot run skips on a laptop and fails in CI as root."""

import pytest

from tests import proof


def test_a_proof_that_cannot_run_fails_in_ci_as_root(monkeypatch):
    monkeypatch.setenv("CI", "true")
    monkeypatch.setattr(proof.os, "geteuid", lambda: 0)
    with pytest.raises(pytest.fail.Exception, match="could not run in CI as root: no nspawn"):
        proof.skip_proof("no nspawn")


@pytest.mark.parametrize("ci, uid", [(None, 0), ("true", 1000), ("false", 0)])
def test_elsewhere_it_skips(monkeypatch, ci, uid):
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    monkeypatch.setattr(proof.os, "geteuid", lambda: uid)
    with pytest.raises(pytest.skip.Exception, match="no nspawn"):
        proof.skip_proof("no nspawn")
