"""The seeded mutation loop: mutate seeds, feed them to a target, collect findings (CI and scripts/fuzz)."""

import hashlib
import random
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from .bounds import Finding
from .mutate import mutate


@dataclass
class CampaignResult:
    """What one run of the loop did."""

    target: str
    cases: int = 0
    seconds: float = 0.0
    findings: list = field(default_factory=list)
    """(sha1 of the input, first line of the finding) per distinct failing input."""
    survivors: list = field(default_factory=list)
    """Inputs kept as extra seeds (they passed): the corpus a later campaign starts from."""


def run_mutations(target, rng: random.Random, *, cases: int | None = None, seconds: float | None = None,
                  findings_dir: Path | None = None, stop_at_first: bool = False,
                  extra_seeds=()) -> CampaignResult:
    """Feed the seeds, then mutants, until `cases` inputs or `seconds` passed; findings saved if asked."""
    result = CampaignResult(target.name)
    target.warm_up()
    pool = target.seeds() + list(extra_seeds)
    corpus = list(pool)
    t0 = time.monotonic()

    def inputs():
        yield from pool
        while True:
            data = mutate(rng.choice(corpus), rng, pool, target.max_len)
            yield target.post_mutate(data, rng)

    for data in inputs():
        if cases is not None and result.cases >= cases:
            break
        if seconds is not None and time.monotonic() - t0 >= seconds:
            break
        result.cases += 1
        try:
            target.check(data)
        except Finding as f:
            digest = hashlib.sha1(data).hexdigest()
            if digest not in {d for d, _ in result.findings}:
                result.findings.append((digest, str(f).splitlines()[0]))
                if findings_dir is not None:
                    findings_dir.mkdir(parents=True, exist_ok=True)
                    (findings_dir / f"{digest}.bin").write_bytes(data)
                    (findings_dir / f"{digest}.txt").write_text(traceback.format_exc())
            if stop_at_first:
                break
        else:
            if len(corpus) < 512 and rng.random() < 0.02:
                corpus.append(data)  # keep a few survivors as seeds: deeper mutants over time
                result.survivors.append(data)
    result.seconds = time.monotonic() - t0
    return result
