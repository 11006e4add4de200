"""The library stands alone: importing any steering_core subpackage loads neither Prefect nor the flows, and its
rooms import only the rooms below them."""

import ast
import subprocess
import sys
from pathlib import Path

SUBPACKAGES = (
    "steering_core",
    "steering_core.data",
    "steering_core.pi05",
    "steering_core.capture",
    "steering_core.sae",
    "steering_core.sae.training.loop",
    "steering_core.sae_quality",
    "steering_core.sae_quality.judge_run",
    "steering_core.vectors",
    "steering_core.remote",
    "steering_core.synthetic",
    "steering_core.evaluate",
    "steering_core.evaluate.run",
    "steering_core.config",
    "steering_core.demo",
    "steering_core.refresh",
    "steering_core.identity",
    "steering_core.preflight",
    "steering_core.workload",
    "steering_core.storage",
    "steering_core.tensor_files",
    "steering_core.reporting",
    "steering_core.serve",
)


def test_library_imports_without_prefect_or_flows():
    """One fresh process imports the subpackages one by one and stops at the first that loads one of those: the
    first to load one is the one that imports it, so one process tells what one process per subpackage would."""
    code = (
        "import importlib, sys\n"
        f"for name in {list(SUBPACKAGES)!r}:\n"
        "    importlib.import_module(name)\n"
        "    bad = sorted(m for m in sys.modules if m.split('.')[0] in ('prefect', 'flows', 'tasks', 'latent_steering_cli'))\n"
        "    if bad:\n"
        "        sys.exit(f'{name} pulled in {bad[:5]}')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-800:]


# steering_core's rooms, lowest first: each imports only rooms before it (type-checking imports aside)
ROOMS = ["storage", "processes", "pairs", "devices", "reporting", "remote", "layout", "identity", "tensor_files", "pi05", "data",
         "capture", "sae", "vectors", "serve", "evaluate", "rollout", "sae_quality", "synthetic", "workload", "config",
         "refresh", "preflight", "demo"]
LIBRARY = Path(__file__).resolve().parents[1] / "steering_core"


def _runtime_imports(tree: ast.AST) -> list[str]:
    """Return the steering_core modules a module imports when it runs (not under `if TYPE_CHECKING:`)."""
    found = []
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("steering_core"):
            found.extend(f"{node.module}.{alias.name}" if node.module == "steering_core" else node.module
                         for alias in node.names)
        elif isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names if alias.name.startswith("steering_core"))
        else:
            found.extend(_runtime_imports(node))
    return found


def test_rooms_import_only_rooms_below_them():
    rooms = {path.stem if path.parent == LIBRARY else path.relative_to(LIBRARY).parts[0]
             for path in LIBRARY.rglob("*.py") if path.name != "__init__.py" or path.parent != LIBRARY}
    assert rooms == set(ROOMS), "a new room of steering_core goes into ROOMS, at its place"
    upward = []
    for path in sorted(LIBRARY.rglob("*.py")):
        if path.parent == LIBRARY and path.name == "__init__.py":
            continue
        room = path.stem if path.parent == LIBRARY else path.relative_to(LIBRARY).parts[0]
        for module in _runtime_imports(ast.parse(path.read_text(encoding="utf-8"))):
            target = module.split(".")[1]
            if target != room and ROOMS.index(target) > ROOMS.index(room):
                upward.append(f"{path.relative_to(LIBRARY.parent)} imports {module}")
    assert not upward, "\n".join(upward)


# the project's packages, lowest first: each imports (at any depth, lazily too) only packages before it
FLOORS = ["steering_core", "tasks", "flows", "deployments", "latent_steering_cli", "bench"]


def _imported_packages(tree: ast.AST) -> set[str]:
    """Return the top-level names of every module `tree` imports anywhere (functions and branches included)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
    return found


def test_packages_import_only_packages_below_them():
    upward = []
    for floor in FLOORS:
        for path in sorted((LIBRARY.parent / floor).rglob("*.py")):
            above = _imported_packages(ast.parse(path.read_text(encoding="utf-8"))) & set(
                FLOORS[FLOORS.index(floor) + 1:])
            upward += [f"{path.relative_to(LIBRARY.parent)} imports {name}" for name in sorted(above)]
    assert not upward, "\n".join(upward)
