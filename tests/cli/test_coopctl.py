"""coopctl as a program: its parser stays light; every command speaks JSON; exit codes are documented."""

import argparse
import json
import os
import subprocess
import sys

import pytest

from coopd.cli import coopctl
from coopd.cli.output import EXITS

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_parser_imports_neither_numpy_nor_numba():
    """status, peers and merge-now start fast: the parser loads no map decoding (numpy, numba kernels)."""
    code = (
        "import sys; from coopd.cli import coopctl; coopctl.build_parser(); "
        "print('numba' in sys.modules or 'numpy' in sys.modules)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": ROOT},
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"


def _leaf_parsers(parser, path=()):
    """(command words, parser) of every runnable coopctl command."""
    groups = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not groups:
        yield path, parser
    for group in groups:
        for name, sub in group.choices.items():
            yield from _leaf_parsers(sub, (*path, name))


def test_every_command_has_json_output():
    leaves = dict(_leaf_parsers(coopctl.build_parser()))
    assert {" ".join(k) for k in leaves} >= {"status", "peers", "merge-now", "dump-map", "map info",
                                              "map convert", "map merge", "key generate", "key check"}
    for words, parser in leaves.items():
        assert "--json" in parser._option_string_actions, words


def test_usage_errors_exit_2_and_are_json_with_json(capsys):
    assert coopctl.main(["status", "--no-such-option"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: coopctl")
    assert err.endswith("coopctl: error: unrecognized arguments: --no-such-option\n")
    assert coopctl.main(["map", "info", "--json"]) == 2
    out = capsys.readouterr().out
    assert json.loads(out) == {"error": "coopctl map info: the following arguments are required: file",
                               "code": "usage", "exit": 2}


def test_help_documents_the_exit_codes(capsys):
    with pytest.raises(SystemExit):
        coopctl.main(["--help"])
    text = capsys.readouterr().out
    assert [e.code for e in EXITS] == list(range(len(EXITS)))  # distinct, no gaps
    for e in EXITS:
        assert f"  {e.code}  {e.name:<12} {e.meaning}" in text


def test_operations_doc_tables_the_same_exit_codes():
    doc = open(os.path.join(ROOT, "docs", "operations.md")).read()
    for e in EXITS:
        assert f"| {e.code} | {e.name} |" in doc, e
