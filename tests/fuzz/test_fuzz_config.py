"""Fuzz config loading: any file gives a Config or a ConfigError (a ValueError) naming the key."""

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import ConfigTarget


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    return ConfigTarget(tmp_path_factory.mktemp("config"))


def test_mutated_files_keep_the_contract(target):
    assert_mutations_clean(target, cases=800)


@CI_SETTINGS
@given(st.randoms(use_true_random=False))
def test_default_file_with_random_values(target, rng: random.Random):
    target.check(target.variant(rng).encode())


@CI_SETTINGS
@given(st.binary(max_size=200))
def test_random_bytes(target, data):
    target.check(data)
