"""Shared pytest setup. tests/ is a package: shared helpers import as tests.<module>
(e.g. tests.synthetic_scenes), and the repository root is on sys.path (pyproject pythonpath)."""

import sys

import pytest

END_TO_END_GROUP = "end-to-end"
"""The pytest-xdist group of the slow tests that run against the wall clock (scripts/test runs with
--dist loadgroup): one worker runs them, one after another."""


def xdist_group_of(item) -> str | None:
    """The xdist group a test runs in, None for a test any worker may take on its own.

    A slow test flies simulated drones in real time against daemons, kills and restarts them, waits
    for timeouts: two at once would compete for the cores each one times itself by, so they all share
    END_TO_END_GROUP. A slow test marked cpu_bound (merges, kernel compiles, flights simulated flat
    out) only takes longer when it shares a core: it runs beside them, in a group of its module so
    that the module's fixtures (flown maps, worlds) are built on one worker only, once."""
    if item.get_closest_marker("slow") is None:
        return None
    if item.get_closest_marker("cpu_bound") is not None:
        return f"cpu-bound:{item.nodeid.split('::')[0]}"
    return END_TO_END_GROUP


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        group = xdist_group_of(item)
        if group is not None and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(group))


@pytest.hookimpl(trylast=True)  # after xdist's hook
def pytest_collection_finish(session):
    """A worker of --dist loadgroup whose grouped tests lost their group stops the run: xdist passes
    the group to its scheduler as an '@group' suffix of the test id, and a pytest that ignores that
    suffix (9.2 with xdist 3.8) spreads the end-to-end tests over every worker without a word."""
    if not (session.config.getoption("loadgroup", False) and hasattr(session.config, "workerinput")):
        return
    lost = [item.nodeid for item in session.items
            if item.get_closest_marker("xdist_group") is not None and "@" not in item.nodeid]
    if lost:
        message = (f"pytest-xdist's loadgroup did not group {len(lost)} tests (first: {lost[0]}): pytest "
                   f"{pytest.__version__} and this pytest-xdist do not work together; see the pytest pin of "
                   "the test extra in pyproject.toml")
        print(message, file=sys.__stderr__, flush=True)  # a worker's exceptions reach the terminal garbled
        raise pytest.UsageError(message)
