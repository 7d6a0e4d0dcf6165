#!/usr/bin/env python3
"""Coverage-guided campaign (atheris/libFuzzer) for one in-process target of tests/fuzz/harness.py.

Usage: scripts/fuzz_atheris.py TARGET --seconds N [--out DIR]   (scripts/fuzz_campaign.py --engine atheris
runs this once per target). libFuzzer keeps its corpus in DIR/<target>/atheris-corpus/, writes a
failing input as DIR/<target>/crash-<sha1> and ends with "Done N runs" on stderr.
"""

import argparse
import sys
import tempfile
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NUMBA_MODULES = [
    "coopd.sharing.codec_kernels", "coopd.sharing.planes_kernels", "coopd.grid.kernels",
    "coopd.mapping.raycast", "coopd.io.bt", *(f"coopd.merging.{m}" for m in (
        "level", "ransac", "preprocess", "matching", "brief3d", "fast3d", "mtm", "orientation",
        "keypoint_filter", "validation", "yaw_search"))]
"""Modules with numba kernels: instrumented bytecode cannot be compiled by numba, so they run as is."""

with atheris.instrument_imports(include=["coopd"], exclude=NUMBA_MODULES):
    import coopd.camera.protocol  # noqa: F401
    import coopd.daemon.config  # noqa: F401
    import coopd.io.cmap  # noqa: F401
    import coopd.sharing.codec  # noqa: F401
    import coopd.sharing.mtp  # noqa: F401
    import coopd.sharing.planes  # noqa: F401
    import coopd.sharing.wire  # noqa: F401
    import coopd.vehicle.link  # noqa: F401

from tests.fuzz import bounds  # noqa: E402
from tests.fuzz.harness import CALL_LIMIT_S, make_target  # noqa: E402

IN_PROCESS = ("codec", "planes", "wire", "cmap", "mtp", "camera_header", "config", "mavlink")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("target", choices=IN_PROCESS)
    ap.add_argument("--seconds", type=int, default=60)
    ap.add_argument("--out", type=Path, default=Path("out/fuzz"))
    args = ap.parse_args()
    target_dir = args.out / args.target
    corpus = target_dir / "atheris-corpus"
    corpus.mkdir(parents=True, exist_ok=True)
    bounds.USE_ALARM = False  # libFuzzer owns SIGALRM; its -timeout reports a hanging input instead
    workdir = tempfile.mkdtemp(prefix="fz")
    target = make_target(args.target, workdir)
    target.warm_up()
    for i, seed in enumerate(target.seeds()):
        (corpus / f"seed-{i}").write_bytes(seed)

    def one_input(data: bytes) -> None:
        target.check(data)  # a Finding propagates: libFuzzer records the input as a crash

    atheris.Setup([sys.argv[0], f"-max_total_time={args.seconds}", f"-timeout={int(2 * CALL_LIMIT_S)}",
                   "-rss_limit_mb=4096", f"-max_len={target.max_len}", f"-artifact_prefix={target_dir}/",
                   str(corpus)], one_input)
    atheris.Fuzz()
    return 0


if __name__ == "__main__":
    sys.exit(main())
