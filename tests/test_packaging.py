"""The drone install (`pip install coopd`, scripts/install) carries the daemon and coopctl only:
no dependency that only the emulator or the map tools use, and no module of the product package
that imports them at load time. scripts/bench install_size measures what that comes to on disk."""

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
EMULATOR_OR_TOOLS = {"mujoco", "pillow", "firmware_sim", "foxglove-sdk", "scipy"}
"""Not on a drone: SciPy too, which only the emulator's scoring and the tests use (no kernel calls LAPACK)."""


def names(requirements) -> set[str]:
    return {r.split(";")[0].split("[")[0].split(">")[0].split("=")[0].split("<")[0].strip().lower()
            for r in requirements}


def test_drone_dependencies_leave_out_the_emulator_and_the_tools():
    assert not names(PROJECT["dependencies"]) & EMULATOR_OR_TOOLS
    extras = PROJECT["optional-dependencies"]
    assert names(extras["sim"]) == {"mujoco", "scipy"} and names(extras["tools"]) == {"pillow"}
    assert names(extras["viewer"]) == {"foxglove-sdk"}
    assert "coopd[sim,tools]" in extras["test"]  # scripts/setup test: everything the tests use
    assert "coopd[viewer]" in extras["test"]


def imported(nodes) -> set[str]:
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module.split(".")[0])
    return found


def at_load(tree: ast.Module) -> list[ast.AST]:
    """The nodes that run when the module loads: not function or method bodies, not TYPE_CHECKING blocks."""
    out, todo = [], list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            continue
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        out.append(node)
        todo.extend(ast.iter_child_nodes(node))
    return out


def test_product_package_never_imports_the_emulator_and_tools_only_on_use():
    problems = []
    for path in sorted((ROOT / "coopd").rglob("*.py")):
        tree = ast.parse(path.read_text())
        name = path.relative_to(ROOT)
        problems += [f"{name} imports {m}" for m in imported(ast.walk(tree)) & {"firmware_sim", "scipy"}]
        on_use = {"mujoco", "PIL", "foxglove"}
        problems += [f"{name} imports {m} when it loads" for m in imported(at_load(tree)) & on_use]
    assert problems == []


def test_the_demo_installs_what_it_runs():
    """scripts/demo sets up its own venv from a fresh clone: it flies firmware_sim (coopd[sim]) and
    writes PNG views (coopd[tools]), which the drone install leaves out."""
    setup = [line.split("#")[0].split() for line in (ROOT / "scripts" / "demo").read_text().splitlines()
             if line.startswith("scripts/setup")]
    assert len(setup) == 1 and {"sim", "tools"} <= set(setup[0][1:]), setup
