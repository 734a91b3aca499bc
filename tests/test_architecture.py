"""Layering of the library (issue 28): no library stage imports the simulator, and the
top-level parts of canopy_kit import each other without cycles.

Every module of ``canopy_kit`` and ``ground_truth`` is parsed with :mod:`ast`, so an import
counts wherever it is written: at module level, inside a function, ``import x.y``,
``from x import y`` or relative.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("canopy_kit", "ground_truth")
SIM = "canopy_kit.sim"

#: Who may import the simulator: itself, the command line, the paper's experiment runner
#: (which simulates sessions); benchmarks/, tests/ and notebooks/ are outside the packages.
SIM_IMPORTERS = ("canopy_kit.sim", "canopy_kit.cli", "canopy_kit.paper.experiments")

#: Cycles of module-level imports between canopy_kit's top-level parts (``canopy_kit.report``,
#: ``canopy_kit.pipeline``...) that are tolerated: none. A cycle, or a part joining one, fails.
ALLOWED_MODULE_LEVEL_CYCLES: list[frozenset[str]] = []

#: Counting the imports made inside functions too (issue 28: "hidden by imports made inside
#: functions"): none. The loop pipeline -> report -> pipeline, segment/results ->
#: paper/comparison -> segment/results and checks <-> pipeline was broken by moving the
#: per-tree table and the run's files out of pipeline (canopy_kit.results.tree_table,
#: canopy_kit.results.outputs) and the segmentation results table into canopy_kit.paper.
ALLOWED_CYCLES_THROUGH_FUNCTION_IMPORTS: list[frozenset[str]] = []


@dataclass(frozen=True)
class Import:
    """One imported module name, where it is written, and whether it runs at import time."""

    module: str  # the importing module
    target: str  # the imported module (``from a import b``: ``a.b`` when that is a module)
    line: int
    module_level: bool  # False inside a function body or an ``if TYPE_CHECKING:`` block


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            out[module_name(path)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def imports_of(name: str, path: Path, known: set[str]) -> list[Import]:
    """Every import in a module, relative ones resolved against its package."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[Import] = []

    def visit(node: ast.AST, module_level: bool) -> None:
        for child in ast.iter_child_nodes(node):
            level = module_level
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                level = False
            if isinstance(child, ast.Import):
                found.extend(Import(name, a.name, child.lineno, module_level) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    anchor = package.split(".")
                    anchor = anchor[: len(anchor) - (child.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                for a in child.names:
                    sub = f"{base}.{a.name}"
                    found.append(
                        Import(name, sub if sub in known else base, child.lineno, module_level)
                    )
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for stmt in child.body:
                    visit(ast.Module(body=[stmt], type_ignores=[]), False)
                for stmt in child.orelse:
                    visit(ast.Module(body=[stmt], type_ignores=[]), level)
                continue
            visit(child, level)

    visit(tree, True)
    return found


def all_imports() -> list[Import]:
    mods = modules()
    known = set(mods)
    return [imp for name, path in mods.items() for imp in imports_of(name, path, known)]


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def forbidden_sim_imports(imports: list[Import]) -> list[str]:
    """``module:line imports target`` for each import of the simulator outside its importers."""
    return [
        f"{imp.module} ({modules()[imp.module].relative_to(ROOT)}:{imp.line}) imports {imp.target}"
        for imp in imports
        if _within(imp.target, SIM) and not any(_within(imp.module, a) for a in SIM_IMPORTERS)
    ]


def part_of(module: str) -> str | None:
    """The top-level part of canopy_kit a module belongs to (``canopy_kit.report``...)."""
    parts = module.split(".")
    if parts[0] != "canopy_kit" or len(parts) < 2:
        return None
    return ".".join(parts[:2])


def part_graph(imports: list[Import], module_level_only: bool) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for imp in imports:
        if module_level_only and not imp.module_level:
            continue
        a, b = part_of(imp.module), part_of(imp.target)
        if a and b and a != b:
            graph.setdefault(a, set()).add(b)
            graph.setdefault(b, set())
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components with more than one part (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[frozenset[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(frozenset(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return out


def _edges_within(
    graph: dict[str, set[str]],
    component: frozenset[str],
    imports: list[Import],
    module_level_only: bool,
) -> list[str]:
    """Where each import along a cycle is written, for the failure message."""
    return sorted(
        f"{imp.module}:{imp.line} -> {imp.target}"
        for imp in imports
        if (imp.module_level or not module_level_only)
        and part_of(imp.module) in component
        and part_of(imp.target) in component
        and part_of(imp.module) != part_of(imp.target)
    )


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    return all_imports()


def test_the_parser_sees_every_kind_of_import(tmp_path: Path) -> None:
    """The checks below are only as good as the parser: it must see nested and relative imports."""
    source = (
        "import canopy_kit.sim.truth\nfrom . import figures\nfrom ..sim import load_truth\n"
        "def f():\n    from canopy_kit import sim\n    import canopy_kit.sim as s\n"
        "if TYPE_CHECKING:\n    from canopy_kit.pipeline import RunContext\n"
    )
    probe = tmp_path / "probe.py"
    probe.write_text(source)
    found = imports_of("canopy_kit.report.probe", probe, set(modules()))
    got = [(i.target, i.line, i.module_level) for i in found]
    assert got == [
        ("canopy_kit.sim.truth", 1, True),
        ("canopy_kit.report.figures", 2, True),
        ("canopy_kit.sim", 3, True),
        ("canopy_kit.sim", 5, False),
        ("canopy_kit.sim", 6, False),
        ("canopy_kit.pipeline", 8, False),
    ]


def test_no_library_stage_imports_the_simulator(imports: list[Import]) -> None:
    bad = forbidden_sim_imports(imports)
    assert not bad, (
        "library stages must not import the simulator (read truth and the session "
        "layout through canopy_kit.evaluate.truth / canopy_kit.io.session_layout):\n  "
        + "\n  ".join(bad)
    )


def _new_cycles(
    imports: list[Import], module_level_only: bool, allowed: list[frozenset[str]]
) -> list[str]:
    """Each cycle that is not inside an allowed one, with the imports along it."""
    graph = part_graph(imports, module_level_only)
    return [
        f"cycle {' <-> '.join(sorted(c))}:\n    "
        + "\n    ".join(_edges_within(graph, c, imports, module_level_only))
        for c in cycles(graph)
        if not any(c <= ok for ok in allowed)
    ]


def test_no_cycle_of_module_level_imports_between_parts(imports: list[Import]) -> None:
    new = _new_cycles(imports, True, ALLOWED_MODULE_LEVEL_CYCLES)
    assert not new, "module-level import cycles between parts of canopy_kit:\n  " + "\n  ".join(new)


def test_no_new_cycle_through_imports_inside_functions(imports: list[Import]) -> None:
    new = _new_cycles(imports, False, ALLOWED_CYCLES_THROUGH_FUNCTION_IMPORTS)
    assert not new, (
        "import cycles between parts of canopy_kit (counting imports inside "
        "functions) beyond ALLOWED_CYCLES_THROUGH_FUNCTION_IMPORTS:\n  " + "\n  ".join(new)
    )


def _loaded_after(imported: list[str], parts: tuple[str, ...]) -> list[str]:
    """The modules of ``parts`` a fresh interpreter has loaded after importing ``imported``."""
    code = (
        f"import sys\nfor m in {imported!r}: __import__(m)\n"
        f"print(sorted(m for m in sys.modules if m.startswith({parts!r})))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    return ast.literal_eval(out.stdout.strip())


def test_segment_and_volume_load_no_simulator_report_paper_or_cli() -> None:
    parts = tuple(f"canopy_kit.{p}" for p in ("sim", "report", "paper", "cli"))
    assert _loaded_after(["canopy_kit.segment.verb", "canopy_kit.volume"], parts) == []


def test_evaluation_and_truth_modules_load_no_simulator() -> None:
    stages = [
        "canopy_kit.evaluate.truth",
        "canopy_kit.evaluate.truth_map",
        "canopy_kit.io.session_layout",
        "canopy_kit.evaluate.segmentation_score",
        "canopy_kit.evaluate.validation",
        "canopy_kit.evaluate.trajectory_error",
        "canopy_kit.evaluate.volume_errors",
        "canopy_kit.pipeline.explore",
        "canopy_kit.segment.export",
        "canopy_kit.paper.segmentation_results",
    ]
    assert _loaded_after(stages, ("canopy_kit.sim",)) == []


#: The layers of canopy_kit, lowest first (docs/ARCHITECTURE.md). A part imports only parts
#: of lower layers (or of its own, where the parts listed together never import each other):
#: the stages (volume, segment, mapping) sit on io, config and core; evaluate scores the
#: stages against truth; results holds what a run hands on; the report, the stream and the
#: store read results; pipeline runs it all; paper, testing and cli stand on top.
LAYERS: list[set[str]] = [
    {"errors"},
    {"core", "plugins"},
    {"config"},
    {"io"},
    {"volume"},
    {"segment"},
    {"evaluate"},
    {"mapping"},  # its plots compare a trajectory with the reference (evaluate)
    {"sim"},
    {"results"},
    {"report", "streaming", "store"},
    {"pipeline"},
    {"paper", "testing"},
    {"cli"},
]


def layer_of(part: str) -> int:
    name = part.removeprefix("canopy_kit.")
    return next(i for i, layer in enumerate(LAYERS) if name in layer)


def test_every_part_has_a_layer_and_few_modules_stand_alone() -> None:
    parts = {part_of(m) for m in modules() if part_of(m)}
    named = {f"canopy_kit.{p}" for layer in LAYERS for p in layer}
    assert parts == named, f"parts without a layer: {parts - named}; gone: {named - parts}"
    loose = sorted(p.name for p in (ROOT / "canopy_kit").glob("*.py") if p.name != "__init__.py")
    assert len(loose) <= 8, f"modules directly under canopy_kit/: {loose}"


def test_imports_only_go_down_the_layers(imports: list[Import]) -> None:
    upward = sorted(
        f"{imp.module}:{imp.line} -> {imp.target}"
        for imp in imports
        if (a := part_of(imp.module))
        and (b := part_of(imp.target))
        and a != b
        and layer_of(b) >= layer_of(a)
    )
    assert not upward, "imports up (or across) the layers of LAYERS:\n  " + "\n  ".join(upward)
