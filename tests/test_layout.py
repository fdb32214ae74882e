"""The package layout holds: the CLI and the tooling packages import no service at module level, the scenario
package has no import cycle, ``zagv map`` never imports localization, and no service is wired by importlib."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVICES = REPO / "services"
#: a service is a package with a node (services/common's node.py is the shared Node class, not a service)
SERVICE_PACKAGES = sorted(p.parent.name for p in SERVICES.glob("*/node.py") if p.parent.name != "common")
#: packages of tooling (argument parsing, starting stacks, scenarios) that must not depend on a service's code
TOOLING = ["cli", "launch", "scenario"]


def imported_modules(tree: ast.Module, *, module_level_only: bool) -> list[tuple[int, str]]:
    """(line, dotted module) of every import; ``module_level_only`` skips imports inside functions and classes."""
    nodes = list(tree.body) if module_level_only else list(ast.walk(tree))
    found: list[tuple[int, str]] = []
    for node in nodes:
        if isinstance(node, ast.If) and module_level_only:  # `if TYPE_CHECKING:` and similar guards count
            nodes.extend(node.body + node.orelse)
        elif isinstance(node, ast.Import):
            found.extend((node.lineno, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.extend((node.lineno, f"{node.module}.{a.name}") for a in node.names)
    return found


def service_imports(source: str, *, module_level_only: bool = True) -> list[str]:
    """``line: module`` of each import of a service package in ``source``."""
    service = re.compile(rf"^services\.({'|'.join(SERVICE_PACKAGES)})(\.|$)")
    return [f"{line}: {name}" for line, name in imported_modules(ast.parse(source), module_level_only=module_level_only)
            if service.match(name)]


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (module -> modules it imports) as a path, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def package_graph(package: Path) -> dict[str, set[str]]:
    """Imports between the modules of ``package``, function-level imports included."""
    modules = {module_name(p): p for p in package.glob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for _, imported in imported_modules(ast.parse(path.read_text()), module_level_only=False):
            for candidate in (imported, imported.rsplit(".", 1)[0]):  # `from pkg import mod`, `from mod import x`
                if candidate in modules and candidate != name:
                    targets.add(candidate)
                    break
        graph[name] = targets
    return graph


def test_the_checks_see_what_they_look_for():
    assert SERVICE_PACKAGES and {"localization", "sim", "nav", "drive"} <= set(SERVICE_PACKAGES)
    source = ("import json\nfrom services.common.world import World\nfrom services.localization.amcl import Amcl\n"
              "if True:\n    import services.sim.node\n"
              "def f():\n    from services.nav import bench\n")
    assert service_imports(source) == ["3: services.localization.amcl.Amcl", "5: services.sim.node"]
    assert service_imports(source, module_level_only=False)[-1] == "7: services.nav.bench"
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


@pytest.mark.parametrize("package", TOOLING)
def test_tooling_imports_no_service_at_module_level(package):
    """cli, launch and scenario reach a service only inside the function that needs it (``zagv bench``'s
    discovery of each service's bench.py, the simulator's fleet placement, ...), never when imported."""
    found = {str(p.relative_to(REPO)): hits for p in sorted((SERVICES / package).glob("*.py"))
             if (hits := service_imports(p.read_text()))}
    assert not found, f"module-level imports of a service package: {found}"


def test_zagv_map_runs_offline_slam_without_importing_localization():
    hits = [h for h in service_imports((SERVICES / "cli" / "map.py").read_text(), module_level_only=False)
            if "localization" in h]
    assert not hits, hits


def test_the_cli_is_argument_parsing():
    """Every command module of services/cli registers a parser; the work lives in the packages it calls."""
    from services.cli.main import COMMANDS

    assert all(callable(getattr(module, "register", None)) for module in COMMANDS)
    moved = {"up.py": "launch", "router.py": "launch", "install_units.py": "launch", "scenario.py": "scenario"}
    for name, package in moved.items():
        text = (SERVICES / "cli" / name).read_text()
        assert f"services.{package}" in text, name
        assert "asyncio" not in text and "subprocess" not in text, f"services/cli/{name} does more than parse"


@pytest.mark.parametrize("package", ["scenario", "launch", "cli"])
def test_no_import_cycle(package):
    graph = package_graph(SERVICES / package)
    assert len(graph) > 1
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle or [])


def test_no_importlib_in_service_wiring():
    """Services are wired by plain imports: ``importlib`` by name hides an entry point (package data through
    ``importlib.resources`` is fine)."""
    allowed = re.compile(r"^\s*(from importlib import resources|import importlib\.resources)\b")
    hits = []
    for path in sorted(SERVICES.rglob("*.py")):
        for k, line in enumerate(path.read_text().splitlines(), 1):
            if "importlib" in line and not allowed.match(line) and "importlib.resources" not in line:
                hits.append(f"{path.relative_to(REPO)}:{k}: {line.strip()}")
    assert not hits, "\n".join(hits)
