#!/usr/bin/env python3
"""Long fuzz campaigns over coopd's outward-facing parsers (the harness of tests/fuzz, time-boxed).

Usage: scripts/fuzz_campaign.py (--all | TARGET ...) [--seconds N] [--cases N] [--seed S] [--out DIR]
                                [--engine mutation|atheris] [--jobs N]
       scripts/fuzz_campaign.py TARGET --replay FILE      re-run one saved input, print its finding
Findings (failing inputs + traceback) go to DIR/<target>/, survivors to DIR/<target>/corpus/ (the
next campaign starts from them), and a summary of cases and findings to DIR/summary.json.
"""

import argparse
import hashlib
import json
import logging
import random
import re
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzz.bounds import Finding  # noqa: E402
from tests.fuzz.campaign import run_mutations  # noqa: E402
from tests.fuzz.harness import TARGETS, make_target  # noqa: E402

MAX_CORPUS_FILES = 256
ATHERIS_TARGETS = ("codec", "planes", "wire", "cmap", "mtp", "camera_header", "config", "mavlink")
"""In-process targets (fuzz_atheris.py); the socket targets always run the mutation loop."""


def load_corpus(directory: Path) -> list[bytes]:
    return [p.read_bytes() for p in sorted(directory.glob("*.bin"))] if directory.is_dir() else []


def save_corpus(directory: Path, inputs) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for data in inputs:
        if len(list(directory.glob("*.bin"))) >= MAX_CORPUS_FILES:
            return
        (directory / f"{hashlib.sha1(data).hexdigest()}.bin").write_bytes(data)


def campaign(name: str, seconds: float, seed: int, out: Path, workdir: str, cases: int | None = None) -> dict:
    """Run one target for `seconds`, or until `cases` inputs when given; its summary entry."""
    target_dir = out / name
    corpus_dir = target_dir / "corpus"
    with make_target(name, workdir) as target:
        result = run_mutations(target, random.Random(seed), cases=cases, seconds=seconds,
                               findings_dir=target_dir, extra_seeds=load_corpus(corpus_dir))
    save_corpus(corpus_dir, result.survivors)
    return {"cases": result.cases, "seconds": round(result.seconds, 1),
            "cases_per_second": round(result.cases / max(result.seconds, 1e-9)),
            "findings": [{"input": str(target_dir / f"{d}.bin"), "finding": msg}
                         for d, msg in result.findings]}


def _shard(args: tuple) -> dict:
    """One process' share of a campaign, in its own working directory (its own sockets)."""
    name, seconds, seed, out, cases = args
    logging.basicConfig(level=logging.CRITICAL)
    with tempfile.TemporaryDirectory(prefix="fz") as workdir:
        return campaign(name, seconds, seed, out, workdir, cases)


def sharded_campaign(name: str, seconds: float, seed: int, out: Path, cases: int | None, jobs: int) -> dict:
    """The campaign split over `jobs` processes, shard i seeded seed + i and given an equal share of the
    cases: the socket targets mostly wait on their peers, so shards add cases per second."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    shares = [None if cases is None else cases // jobs + (i < cases % jobs) for i in range(jobs)]
    with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
        parts = list(pool.map(_shard, [(name, seconds, seed + i, out, shares[i]) for i in range(jobs)]))
    n = sum(p["cases"] for p in parts)
    wall = max(p["seconds"] for p in parts)
    return {"cases": n, "seconds": wall, "cases_per_second": round(n / max(wall, 1e-9)), "jobs": jobs,
            "findings": [f for p in parts for f in p["findings"]]}


def atheris_campaign(name: str, seconds: float, out: Path) -> dict:
    """Run one in-process target under atheris (coverage-guided libFuzzer) in a child; its summary entry."""
    target_dir = out / name
    target_dir.mkdir(parents=True, exist_ok=True)
    before = set(target_dir.glob("crash-*")) | set(target_dir.glob("timeout-*"))
    t0 = time.monotonic()
    child = subprocess.run(
        [sys.executable, str(Path(__file__).with_name("fuzz_atheris.py")), name, "--seconds",
         str(max(1, int(seconds))), "--out", str(out)], capture_output=True, text=True, errors="replace",
        timeout=seconds + 120)
    elapsed = time.monotonic() - t0
    (target_dir / "atheris.log").write_text(child.stderr[-200_000:])
    runs = re.findall(r"^(?:Done (\d+) runs|#(\d+)\s)", child.stderr, re.M)
    cases = max((int(a or b) for a, b in runs), default=0)
    new = sorted((set(target_dir.glob("crash-*")) | set(target_dir.glob("timeout-*"))) - before)
    findings = [{"input": str(p), "finding": _finding_line(child.stderr)} for p in new]
    if child.returncode != 0 and not findings:
        findings.append({"input": None, "finding": f"atheris exited with {child.returncode}; see "
                                                   f"{target_dir / 'atheris.log'}"})
    rate = round(cases / max(elapsed, 1e-9))
    return {"cases": cases, "seconds": round(elapsed, 1), "cases_per_second": rate, "findings": findings}


def _finding_line(log: str) -> str:
    lines = [line for line in log.splitlines() if "Finding:" in line or "Error:" in line]
    return lines[-1].strip() if lines else "see atheris.log"


def replay(name: str, path: Path, workdir: str) -> int:
    with make_target(name, workdir) as target:
        target.warm_up()
        try:
            target.check(path.read_bytes())
        except Finding:
            traceback.print_exc()
            return 1
    print(f"{path}: no finding")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("targets", nargs="*", help=f"targets: {', '.join(TARGETS)}")
    ap.add_argument("--all", action="store_true", help="every target, one after the other")
    ap.add_argument("--seconds", type=float, default=None,
                    help="time budget per target (default 60; with --cases a cap, default 3600)")
    ap.add_argument("--cases", type=int, default=None,
                    help="mutation engine: stop each target after this many cases (within --seconds)")
    ap.add_argument("--seed", type=int, default=None, help="mutation RNG seed (default: time-based)")
    ap.add_argument("--out", type=Path, default=Path("out/fuzz"))
    ap.add_argument("--engine", choices=("mutation", "atheris"), default="mutation",
                    help="atheris: coverage-guided, in-process targets only (socket targets use mutation)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="mutation engine: split each target's campaign over N processes (seeds S..S+N-1)")
    ap.add_argument("--replay", type=Path, help="re-run one saved input against the (single) target")
    ap.add_argument("--verbose", action="store_true", help="show the parsers' own log messages")
    args = ap.parse_args(argv)
    if args.seconds is None:
        args.seconds = 3600.0 if args.cases else 60.0
    logging.basicConfig(level=logging.INFO if args.verbose else logging.CRITICAL)
    names = list(TARGETS) if args.all else args.targets
    unknown = [n for n in names if n not in TARGETS]
    if not names or unknown:
        ap.error(f"name targets or --all; unknown: {unknown}; known: {', '.join(TARGETS)}")
    with tempfile.TemporaryDirectory(prefix="fz") as workdir:  # short: unix socket paths live here
        if args.replay:
            if len(names) != 1:
                ap.error("--replay takes exactly one target")
            return replay(names[0], args.replay, workdir)
        seed = args.seed if args.seed is not None else time.time_ns() % 2**32
        summary_path = args.out / "summary.json"
        summary = {"targets": {}}
        for name in names:
            engine = args.engine if name in ATHERIS_TARGETS else "mutation"
            if engine == "atheris":
                entry = atheris_campaign(name, args.seconds, args.out)
            elif args.jobs > 1:
                entry = sharded_campaign(name, args.seconds, seed, args.out, args.cases, args.jobs)
            else:
                entry = campaign(name, args.seconds, seed, args.out, workdir, args.cases)
            finished = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            entry.update(seed=seed, engine=engine, finished=finished)
            found = len(entry["findings"])
            print(f"{name}: {entry['cases']} cases in {entry['seconds']} s, {found} findings", flush=True)
            args.out.mkdir(parents=True, exist_ok=True)
            # re-read: a campaign running beside this one may have written its own target meanwhile
            summary = json.loads(summary_path.read_text()) if summary_path.exists() else {"targets": {}}
            summary["targets"][name] = entry
            summary["total_cases"] = sum(t["cases"] for t in summary["targets"].values())
            summary["total_findings"] = sum(len(t["findings"]) for t in summary["targets"].values())
            summary_path.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"summary: {summary_path}")
    return 1 if any(summary["targets"][n]["findings"] for n in names) else 0


if __name__ == "__main__":
    sys.exit(main())
