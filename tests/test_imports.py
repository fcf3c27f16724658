"""What importing spheroseg costs: neither numba nor matplotlib until used."""

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest


SRC = str(Path(__file__).resolve().parents[1] / "src")
HEAVY = ("numba", "matplotlib")


def loaded_after(code: str) -> dict:
    """``{module: loaded}`` for HEAVY after running ``code`` in a fresh interpreter."""
    probe = code + f"\nimport json, sys\nprint(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))"
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_loads_neither_numba_nor_matplotlib():
    assert loaded_after("import spheroseg") == {"numba": False, "matplotlib": False}


def test_cli_help_loads_neither_numba_nor_matplotlib():
    code = ("import sys\nfrom spheroseg.cli import main\n"
            "for argv in (['--help'], ['segment', '--help'], ['track', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass")
    assert loaded_after(code) == {"numba": False, "matplotlib": False}


def test_the_probe_sees_a_heavy_import():
    # the checks above can fail: the compiled sector-padding pass loads numba
    code = "import numpy as np\nfrom spheroseg.volume import outside_sector\noutside_sector(np.zeros((3, 3, 3)))"
    assert loaded_after(code)["numba"] is True


PACKAGE = Path(SRC) / "spheroseg"
#: the layers below the iteration: geometry and images know nothing of the
#: compiled kernels, the numba runtime or the orchestration above them
#: (``surface`` and ``volume`` reach the rasteriser through the service
#: ``raster`` only, which imports neither of them)
LOWER = ("coords", "hermite", "surface", "volume", "energy", "discretisation", "dataterms")
FORBIDDEN_BELOW = ("_kernels", "_raster", "_runtime", "backends", "descent", "stepper", "frames",
                   "initial", "tracker", "segment", "warmup", "batch", "cli", "outputs", "io")
#: the compiled kernels and the runtime import no orchestration
COMPILED = ("_kernels", "_raster", "_runtime", "raster")
ORCHESTRATION = ("backends", "descent", "stepper", "frames", "initial", "tracker", "segment", "warmup", "batch", "cli",
                 "outputs", "io", "viewer")


def import_graph(package: Path = PACKAGE) -> dict:
    """``{module: {imported module: first line}}`` within the package, from
    every import statement of every module (those inside functions and
    under ``if`` included); ``from . import x`` counts as importing the
    submodule ``x``, not the package."""
    names = {}
    for path in package.rglob("*.py"):
        parts = path.relative_to(package.parent).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in names.items():
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = graph.setdefault(name, {})
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([node.module] if node.module else []))
                subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in names]
                targets = subs + ([base] if len(subs) < len(node.names) else [])
            else:
                continue
            for target in targets:
                if target in names and target != name:
                    edges.setdefault(target, node.lineno)
    return graph


def cycles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_package_has_no_import_cycle():
    assert cycles(import_graph()) == []


def test_the_cycle_search_finds_a_cycle(tmp_path):
    # the check above can fail: a function-level import closing a loop
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from . import b\n")
    (package / "b.py").write_text("def f():\n    from .c import g\n")
    (package / "c.py").write_text("import pkg.a\n")
    (package / "d.py").write_text("from .a import x\n")
    assert cycles(import_graph(package)) == [["pkg.a", "pkg.b", "pkg.c"]]


def offences(graph: dict, lower: tuple, forbidden: tuple) -> list:
    prefix = PACKAGE.name + "."
    return [f"{m} imports {t} (line {line})" for m in map(prefix.__add__, lower)
            for t, line in graph.get(m, {}).items() if t.removeprefix(prefix).split(".")[0] in forbidden]


def test_geometry_and_images_import_nothing_compiled_or_above():
    assert offences(import_graph(), LOWER, FORBIDDEN_BELOW) == []


def test_compiled_code_imports_no_orchestration():
    assert offences(import_graph(), COMPILED, ORCHESTRATION) == []


def test_no_module_reaches_the_package_init():
    # ``from . import __version__`` would load every front end (batch, io)
    graph = import_graph()
    assert [m for m, edges in graph.items() if "spheroseg" in edges and m != "spheroseg.__main__"] == []


def test_the_method_never_imports_the_synthetic_data():
    # the phantom is the ground truth the method is measured on, not a part of
    # it: only the demo's front ends and the deprecated aliases reach it
    graph = import_graph()
    users = sorted(m for m, edges in graph.items() if not m.startswith("spheroseg.synthetic")
                   and any(t.startswith("spheroseg.synthetic") for t in edges))
    assert users == ["spheroseg.batch", "spheroseg.cli", "spheroseg.echo", "spheroseg.phantom"]


@pytest.mark.parametrize("name", ["phantom", "echo"])
def test_the_old_names_of_the_synthetic_modules_are_deprecated_aliases(name):
    code = (f"import warnings\nwarnings.simplefilter('error')\ntry:\n    import spheroseg.{name}\n"
            f"except DeprecationWarning as w:\n    print(w)\nwarnings.simplefilter('ignore')\n"
            f"import spheroseg.{name}, spheroseg.synthetic.{name}\n"
            f"print(spheroseg.{name} is spheroseg.synthetic.{name})")
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split("\n")[:2] == [f"spheroseg.{name} moved to spheroseg.synthetic.{name}; the old name "
                                          "goes in the next release", "True"]
