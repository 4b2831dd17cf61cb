"""The dependency rule as a test: every module's imports (module level and inside functions) are
read from its AST, and three things fail the build:

1. an import against the direction runtime <- sim <- training <- export <- cmnav (a package may
   import the ones to its left, never one to its right; ``bench`` may import them all, ``tests``
   anything: they are not checked);
2. ``sim`` or ``training`` importing ``runtime`` beyond the contract and the few shared types
   named in :data:`SHARED_FROM_RUNTIME` (and the per-module exceptions of
   :data:`EXTRA_FROM_RUNTIME`, each with its reason);
3. any import cycle between modules (imports under ``if TYPE_CHECKING:`` excluded: they never run);
4. an import of a module of these packages that the tree does not have (in ``tests`` too): after a
   move, the editable install would otherwise find the old file in another checkout.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Left to right: each package may import those before it.
LAYERS = ("runtime", "sim", "training", "export", "cmnav")
IMPORTS_ALL = ("bench",)
UNCHECKED = ("tests",)  # may import anything; only checked for imports of missing modules

# What sim and training may take from runtime: the contract and these shared types (a module, or
# a package with everything under it).
SHARED_FROM_RUNTIME = (
    "runtime.contract",  # the contract: constants, frames, images, action, observation, metadata
    "runtime.state",  # VehicleState, StatusText: pure data
    "runtime.camera.frame",  # the camera Frame every source yields, the SITL camera too
    "runtime.camera.sim_wire",  # the SITL camera link's wire format, written by sim, read by runtime
    "runtime.log.topics",  # the flight log's topic names (sim reads logs)
    "runtime.faults.catalogue",  # the fault kinds and their KIND@SECONDS syntax, shared by both sides
    "runtime.config",  # the runtime's thresholds the follower's judge applies (WatchdogConfig)
    "runtime.service.paths",  # the output directory check, with its message
)
# Module -> runtime modules it may import besides the shared ones, with the reason.
EXTRA_FROM_RUNTIME = {
    # `cmnav sitl` refuses a model the runtime would refuse before it starts any process.
    # ... and writes the flight report beside the log it merged the summary of.
    "sim.sitl_session": ("runtime.model", "runtime.report"),
    # The identification sequence flies through the runtime's own MAVSDK adapter: the command
    # path the runtime flies, on PX4 and on our vehicle alike.
    "sim.response.flight": ("runtime.vehicle",),
    # Recorded PX4 flights are read back with the flight log's one reader (its cut-file and
    # contract-version checks included), not a second copy of the format.
    "sim.response.replay": ("runtime.log.reader",),
}


def _modules(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the packages (a package is its __init__)."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(module: str, path: Path, known: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """(imported module, line, under TYPE_CHECKING) for each import of ``module``; a
    ``from X import Y`` names X.Y where that is a module, else X."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, typing_only: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                for stmt in child.body:
                    visit_stmt(stmt, True)
                for stmt in child.orelse:
                    visit_stmt(stmt, typing_only)
                continue
            visit_stmt(child, typing_only)

    def visit_stmt(node: ast.AST, typing_only: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend((alias.name, node.lineno, typing_only) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.append((sub if sub in known else target, node.lineno, typing_only))
        visit(node, typing_only)

    visit(tree, False)
    return found


def _allowed_from_runtime(module: str, imported: str) -> bool:
    allowed = SHARED_FROM_RUNTIME + EXTRA_FROM_RUNTIME.get(module, ())
    return any(imported == name or imported.startswith(name + ".") for name in allowed)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            connect(node)
    return components


def layering_violations(root: Path) -> list[str]:
    """Every break of the rule in the tree at ``root``, one line each (empty: none)."""
    known = _modules(root, LAYERS + IMPORTS_ALL + UNCHECKED)
    rank = {package: i for i, package in enumerate(LAYERS)}
    problems: list[str] = []
    graph: dict[str, set[str]] = {name: set() for name in known}
    for module, path in known.items():
        package = module.split(".")[0]
        where = path.relative_to(root)
        for imported, line, typing_only in _imports(module, path, known):
            top = imported.split(".")[0]
            if top in LAYERS + IMPORTS_ALL + UNCHECKED and imported not in known:
                problems.append(f"{where}:{line}: {module} imports {imported}, which this tree does not have")
            if imported in known and not typing_only and imported != module:
                graph[module].add(imported)
            if package in IMPORTS_ALL + UNCHECKED or top not in rank:
                continue
            if rank[top] > rank[package]:
                problems.append(f"{where}:{line}: {module} imports {imported}, against {' <- '.join(LAYERS)}")
            elif top == "runtime" and package in ("sim", "training") and not _allowed_from_runtime(module, imported):
                problems.append(f"{where}:{line}: {module} imports {imported}: {package} may take from runtime only "
                                f"{', '.join(SHARED_FROM_RUNTIME)}")  # fmt: skip
    problems.extend(f"import cycle: {' <-> '.join(cycle)}" for cycle in _cycles(graph))
    return list(dict.fromkeys(problems))  # one line per import, not per imported name


def test_the_tree_keeps_the_dependency_rule():
    assert layering_violations(ROOT) == []


def _plant(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return root


CLEAN = {
    "runtime/__init__.py": "",
    "runtime/contract.py": "LIMIT = 1\n",
    "runtime/model.py": "from .contract import LIMIT\n",
    "sim/__init__.py": "",
    "sim/world.py": "from runtime.contract import LIMIT\n",
    "training/__init__.py": "",
    "training/env.py": "import sim.world\n",
    "export/__init__.py": "",
    "export/onnx.py": "from training import env\nfrom runtime.model import LIMIT\n",
    "cmnav/__init__.py": "",
    "cmnav/cli.py": "from export.onnx import LIMIT\n",
    "bench/__init__.py": "",
    "bench/all.py": "import cmnav.cli\n",
}


def test_a_clean_planted_tree_passes(tmp_path):
    assert layering_violations(_plant(tmp_path, CLEAN)) == []


def test_a_planted_upward_import_fails(tmp_path):
    root = _plant(tmp_path, {**CLEAN, "training/env.py": "import sim.world\n\n\ndef later():\n    import export\n"})
    (problem,) = layering_violations(root)
    assert problem.startswith("training/env.py:5: training.env imports export, against runtime <- sim")


def test_a_planted_reach_into_the_runtime_fails(tmp_path):
    root = _plant(tmp_path, {**CLEAN, "sim/world.py": "from runtime.model import LIMIT\n"})
    (problem,) = layering_violations(root)
    assert "sim.world imports runtime.model: sim may take from runtime only runtime.contract" in problem


def test_a_planted_import_of_a_missing_module_fails(tmp_path):
    root = _plant(tmp_path, {**CLEAN, "tests/__init__.py": "", "tests/test_world.py": "from sim.old_world import LIMIT\n"})
    assert layering_violations(root) == ["tests/test_world.py:1: tests.test_world imports sim.old_world, which this tree does not have"]


def test_a_planted_cycle_fails_unless_typing_only(tmp_path):
    cycle = {**CLEAN, "runtime/contract.py": "from . import model\nLIMIT = 1\n"}
    assert layering_violations(_plant(tmp_path / "cycle", cycle)) == ["import cycle: runtime.contract <-> runtime.model"]
    typing_only = {**CLEAN, "runtime/contract.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import model\nLIMIT = 1\n"}
    assert layering_violations(_plant(tmp_path / "typing", typing_only)) == []


def test_runtime_top_level_holds_the_loop_and_its_parts_only():
    """runtime/ is grouped by role (docs/architecture.md): at most 12 modules at its top level; the
    log, process plumbing, programs and fault injection live in their folders."""
    top = sorted(p.stem for p in (ROOT / "runtime").glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 12, top
    assert {"log", "service", "programs", "faults", "camera", "contract"} <= {p.name for p in (ROOT / "runtime").iterdir() if p.is_dir()}
