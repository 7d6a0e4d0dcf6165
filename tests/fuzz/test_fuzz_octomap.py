"""Fuzz the OctoMap reader: hostile .bt / .ot files give a ValueError, never more cells than allowed."""

from hypothesis import given
from hypothesis import strategies as st

from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import OctomapTarget

OCTOMAP = OctomapTarget()


def test_mutated_seeds_keep_the_contract():
    assert_mutations_clean(OCTOMAP)


@CI_SETTINGS
@given(st.sampled_from([b"# Octomap OcTree binary file\nid OcTree\nsize 9\nres 0.1\ndata\n",
                        b"# Octomap OcTree file\nid ColorOcTree\nsize 3\nres 0.05\ndata\n"]),
       st.binary(max_size=200))
def test_random_trees_after_a_valid_header(header, tree):
    OCTOMAP.check(header + tree)
