"""Size of the drone install: this checkout's wheel installed without extras into a fresh venv as
scripts/install does (setuptools removed), and the venv's site-packages summed per distribution.

Prints JSON and writes out/bench/install_size.json. The goal: at most 600 MB, and nothing in it
that only the emulator (mujoco and its GL/UI packages) or the map tools (Pillow) use.
Usage: scripts/bench install_size [--extras sim,tools] [--keep DIR]
"""

import argparse
import json
import subprocess
import sys
import tempfile
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GOAL_MB = 600
NOT_ON_A_DRONE = {"mujoco", "glfw", "pyopengl", "pillow", "absl-py", "etils", "scipy"}
"""Distributions only the emulator (coopd[sim]), the map tools (coopd[tools]) or the tests need."""

MEASURE = r"""
import json, os, sys
from importlib import metadata
site = next(p for p in sys.path if p.endswith("site-packages"))
sizes = {}
for dist in metadata.distributions(path=[site]):
    total = 0
    for f in dist.files or ():
        p = dist.locate_file(f)
        if os.path.isfile(p):
            total += os.path.getsize(p)
    sizes[dist.metadata["Name"].lower()] = total
on_disk = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(site) for f in fs
              if not os.path.islink(os.path.join(d, f)))
print(json.dumps({"site_packages": site, "bytes_on_disk": on_disk, "per_distribution": sizes}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extras", default="", help="extras to add (default none: the drone install)")
    ap.add_argument("--keep", type=Path, help="build the venv here and keep it (default: a temp dir)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        dist = Path(tmp) / "dist"
        subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dist), str(ROOT)],
                       check=True)
        (wheel,) = dist.glob("coopd-*.whl")
        env_dir = args.keep or Path(tmp) / "venv"
        venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
        py = str(env_dir / "bin" / "python")
        spec = f"{wheel}[{args.extras}]" if args.extras else str(wheel)
        # -I: neither this checkout (the current directory) nor PYTHONPATH counts as coopd installed;
        # setuptools goes as scripts/install removes it
        subprocess.run([py, "-I", "-m", "pip", "install", "-q", spec], check=True)
        subprocess.run([py, "-I", "-m", "pip", "uninstall", "-q", "-y", "setuptools"], check=True)
        measured = json.loads(subprocess.run([py, "-I", "-c", MEASURE], check=True, capture_output=True,
                                             text=True).stdout)
    if "coopd" not in measured["per_distribution"]:
        raise SystemExit("install_size: coopd itself did not install into the venv")
    sizes = measured["per_distribution"]
    mb = {name: round(n / 1e6, 1) for name, n in sorted(sizes.items(), key=lambda kv: -kv[1])}
    total_mb = round(measured["bytes_on_disk"] / 1e6, 1)
    result = {
        "benchmark": "install_size",
        "extras": args.extras or "none (the drone install)",
        "site_packages_mb": total_mb,
        "goal_mb": GOAL_MB,
        "within_goal": total_mb <= GOAL_MB,
        "emulator_or_tools_packages": sorted(NOT_ON_A_DRONE & set(sizes)),
        "per_distribution_mb": mb,
        "python": sys.version.split()[0],
    }
    text = json.dumps(result, indent=2)
    print(text)
    out = ROOT / "out" / "bench" / "install_size.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
