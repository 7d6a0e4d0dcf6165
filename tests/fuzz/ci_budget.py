"""The CI budget of the fuzz tests: hypothesis settings and mutation cases per target (~60 s in all)."""

import random

from hypothesis import HealthCheck, settings

from .campaign import run_mutations

CI_EXAMPLES = 150
MUTATION_CASES = 1500
"""Mutants per in-process target in CI; socket targets use fewer (each case is a connection)."""

CI_SETTINGS = settings(max_examples=CI_EXAMPLES, deadline=None, database=None, derandomize=True,
                       suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                              HealthCheck.filter_too_much])


def assert_mutations_clean(target, cases: int = MUTATION_CASES, seed: int = 0) -> int:
    """Run `cases` seeded mutants through target; fail with the first findings. Returns cases run."""
    result = run_mutations(target, random.Random(seed), cases=cases)
    assert not result.findings, f"{target.name}: {len(result.findings)} findings, e.g. {result.findings[:3]}"
    assert result.cases == cases
    return result.cases
