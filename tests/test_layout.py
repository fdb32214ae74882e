"""The package layout holds: the CLI only parses arguments, the tooling packages import no service at module level,
the scenario package has no import cycle, ``zagv map`` never imports localization, and no service is wired by
importlib."""

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
TOOLING = ["cli", "launch", "scenario", "client"]


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


#: modules of I/O and concurrency: a cli module that imports one does the work itself instead of calling it
CLI_FORBIDDEN_IMPORTS = {"zenoh", "asyncio", "queue", "socket", "subprocess", "time", "termios", "tty", "msgspec",
                         "numpy", "threading"}
#: ``threading`` in main.py only asks whether it runs on the main thread before installing the SIGTERM handler
CLI_ALLOWED_IMPORTS = {"main.py": {"threading", "signal"}}
#: a function that is not a parser definition may have this many lines (def line included): a call, a few conversions
CLI_MAX_FUNCTION_LINES = 12


def is_parser_definition(name: str) -> bool:
    return name in ("register", "build_parser") or name.startswith(("add_", "_add_"))


def cli_violations(source: str, allowed_imports: frozenset[str] = frozenset()) -> list[str]:
    """What makes a cli module more than argument parsing: a class, an import of an I/O or concurrency module, a
    function other than a parser definition longer than ``CLI_MAX_FUNCTION_LINES``."""
    tree = ast.parse(source)
    found = []
    for line, name in imported_modules(tree, module_level_only=False):
        top = name.split(".")[0]
        if top in CLI_FORBIDDEN_IMPORTS and top not in allowed_imports:
            found.append(f"{line}: imports {top}")
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            found.append(f"{node.lineno}: class {node.name}")
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not is_parser_definition(node.name):
            lines = (node.end_lineno or node.lineno) - node.lineno + 1
            if lines > CLI_MAX_FUNCTION_LINES:
                found.append(f"{node.lineno}: {node.name} is {lines} lines")
    return found


def test_the_cli_rule_sees_what_it_looks_for():
    long_body = "".join(f"    x{k} = {k}\n" for k in range(CLI_MAX_FUNCTION_LINES))
    source = ("import argparse\nimport zenoh\nfrom queue import Queue\n"
              "class LogClock:\n    pass\n"
              f"def run(args):\n{long_body}"
              f"def register(sub):\n{long_body}"
              "def run_short(args):\n    return 0\n")
    assert cli_violations(source) == ["2: imports zenoh", "3: imports queue", "4: class LogClock",
                                      f"6: run is {CLI_MAX_FUNCTION_LINES + 1} lines"]
    assert cli_violations("import threading\n", frozenset({"threading"})) == []


def test_the_cli_is_argument_parsing():
    """Every command module of services/cli registers a parser and hands the work to the package that does it:
    no classes, no I/O or concurrency modules, no function but parser definitions over a few lines."""
    from services.cli.main import COMMANDS

    assert all(callable(getattr(module, "register", None)) for module in COMMANDS)
    found = {path.name: hits for path in sorted((SERVICES / "cli").glob("*.py"))
             if (hits := cli_violations(path.read_text(), frozenset(CLI_ALLOWED_IMPORTS.get(path.name, set()))))}
    assert not found, f"services/cli does more than parse arguments: {found}"


@pytest.mark.parametrize("package", ["scenario", "launch", "cli", "client"])
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


#: top-level modules whose import marks a module as doing I/O (not a pure core): transports, processes, threads, files
IO_MODULES = frozenset({
    "zenoh", "asyncio", "socket", "subprocess", "sqlite3", "httpx", "threading", "can", "canopen", "serial", "amqtt",
    "aiomqtt", "websockets", "foxglove", "mcap", "rosbags", "argparse", "uvicorn", "http", "signal", "os", "shutil",
    "tempfile",
})


def core_modules() -> list[str]:
    """Service modules that are pure cores: not a node, entry point or bench, outside the tooling packages, and
    importing none of ``IO_MODULES`` at any level."""
    cores = []
    for path in sorted(SERVICES.rglob("*.py")):
        rel = path.relative_to(SERVICES).parts
        if rel[0] in TOOLING or path.name in ("node.py", "__main__.py", "__init__.py") or path.name.startswith("bench"):
            continue
        imported = {name.split(".")[0] for _, name in imported_modules(ast.parse(path.read_text()),
                                                                        module_level_only=False)}
        if not imported & IO_MODULES:
            cores.append(module_name(path))
    return cores


def test_every_core_module_is_type_checked_strictly():
    import tomllib

    overrides = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]["overrides"]
    strict = {m for o in overrides if o.get("disallow_untyped_defs") for m in o["module"]}
    cores = core_modules()
    assert "services.localization.amcl" in cores and "services.nav.node" not in cores
    missing = [m for m in cores if m not in strict]
    assert not missing, f"pure core modules missing from the strict mypy override in pyproject.toml: {missing}"


#: test helpers with one home each: (what, pattern of a definition, the one file allowed to define it)
TEST_HELPERS = [
    ("router process class", re.compile(r"^class \w*Router\w*\b", re.M), "tests/support/router.py"),
    ("free loopback port", re.compile(r"\.bind\(\(\s*\"127\.0\.0\.1\",\s*0\s*\)\)"), "services/common/ports.py"),
    ("router fixture", re.compile(r"^def router\(", re.M), "tests/conftest.py"),
]


def helper_definitions(files: list[Path]) -> list[str]:
    """Definitions of the ``TEST_HELPERS`` outside their home file."""
    found = []
    for path in files:
        rel = path.relative_to(REPO).as_posix()
        text = path.read_text(encoding="utf-8")
        for what, pattern, home in TEST_HELPERS:
            if rel != home and pattern.search(text):
                found.append(f"{rel}: {what} (its home is {home})")
    return found


def test_one_router_class_one_router_fixture_one_free_port():
    files = [p for folder in ("services", "tests", "tools") for p in sorted((REPO / folder).rglob("*.py"))
             if "node_modules" not in p.parts and p.name != "test_layout.py"]
    copies = helper_definitions(files)
    assert not copies, "use the one definition instead of a copy:\n" + "\n".join(copies)


def test_the_helper_rule_sees_a_copy(tmp_path):
    copy = REPO / "tests" / "_copy_probe.py"
    samples = ['class Router:\n    pass\n', 's.bind(("127.0.0.1", 0))\n', 'def router(free_port):\n    pass\n']
    for sample in samples:
        copy.write_text(sample)
        try:
            assert helper_definitions([copy]), sample
        finally:
            copy.unlink()
