"""What importing spheroseg costs: none of the heavy libraries until used, and never numba."""

import ast
import json
import os
import subprocess
import sys
from pathlib import Path


from conftest import SUBPROCESS_PATH

SRC = str(Path(__file__).resolve().parents[1] / "src")
#: what ``import spheroseg`` and the command's --help must not load: each is
#: imported where it is used (SciPy's submodules, SimpleITK by the readers,
#: matplotlib by the report, meshio by the mesh writers, the compiled
#: kernels when first called); numba is no dependency any more
HEAVY = ("numba", "matplotlib", "scipy", "SimpleITK", "meshio", "tqdm", "spheroseg._compiled._raster")
NONE_LOADED = dict.fromkeys(HEAVY, False)


def loaded_after(code: str) -> dict:
    """``{module: loaded}`` for HEAVY after running ``code`` in a fresh interpreter."""
    probe = code + f"\nimport json, sys\nprint(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))"
    env = dict(os.environ, PYTHONPATH=SUBPROCESS_PATH)
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_loads_none_of_the_heavy_libraries():
    assert loaded_after("import spheroseg") == NONE_LOADED


def test_the_public_names_are_all_there():
    # read lazily, each name of __all__ is the object of its module
    code = ("import spheroseg, json\n"
            "print(json.dumps({n: getattr(spheroseg, n).__module__.startswith('spheroseg.') for n in spheroseg.__all__}))")
    env = dict(os.environ, PYTHONPATH=SUBPROCESS_PATH)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    import spheroseg

    assert json.loads(out.stdout) == dict.fromkeys(spheroseg.__all__, True)
    assert set(spheroseg.__all__) <= set(dir(spheroseg))


def test_cli_help_loads_none_of_the_heavy_libraries():
    code = ("import sys\nfrom spheroseg.apps.cli import main\n"
            "for argv in (['--help'], ['segment', '--help'], ['track', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass")
    assert loaded_after(code) == NONE_LOADED


def test_the_probe_sees_a_heavy_import():
    # the checks above can fail: each heavy library imported is seen, the
    # sector-padding pass loads the compiled rasteriser (where built),
    # segment's data terms SciPy
    from spheroseg._compiled._runtime import compiled_available

    seen = loaded_after("import matplotlib, scipy.ndimage, SimpleITK, meshio, tqdm")
    assert seen == {**dict.fromkeys(HEAVY, True), "numba": False, "spheroseg._compiled._raster": False}
    code = "import numpy as np\nfrom spheroseg.volumes.volume import outside_sector\noutside_sector(np.zeros((3, 3, 3)))"
    assert loaded_after(code)["spheroseg._compiled._raster"] is compiled_available()
    assert loaded_after("import spheroseg\nspheroseg.segment")["scipy"] is True


PACKAGE = Path(SRC) / "spheroseg"
#: the layers, bottom first: a module of a folder imports only its own
#: folder, the folders before it here, and the top's own ``_version`` and
#: ``_moved`` (never the package's ``__init__``, which loads every layer)
LAYERS = ("geometry", "_compiled", "volumes", "surfaces", "synthetic", "descent", "tracking", "io", "apps")
#: the modules at the top besides the folders
TOP = ("__init__", "__main__", "_version", "_moved")
ANYWHERE = ("spheroseg._version", "spheroseg._moved")


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


def folder(module: str) -> str | None:
    """The layer folder of a dotted module (``spheroseg.io.images`` -> ``io``), None at the top."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def offences(graph: dict, layers: tuple = LAYERS) -> list:
    """Each import of a folder's module that reaches a folder above its own,
    or the package's ``__init__``."""
    found = []
    for module, edges in graph.items():
        here = folder(module)
        if here is None:
            continue
        allowed = layers[: layers.index(here) + 1]
        for target, line in edges.items():
            if target not in ANYWHERE and folder(target) not in allowed:
                found.append(f"{module} imports {target} (line {line})")
    return sorted(found)


def test_a_folder_imports_only_the_folders_below_it():
    assert offences(import_graph()) == []


def test_the_folder_rule_finds_an_import_running_up(tmp_path):
    # the check above can fail: a function-level import of a higher folder,
    # and one of the package's __init__
    package = tmp_path / "spheroseg"
    for name in ("", "geometry", "apps"):
        (package / name).mkdir(exist_ok=True)
        (package / name / "__init__.py").write_text("")
    (package / "geometry" / "coords.py").write_text("def f():\n    from ..apps.cli import main\n")
    (package / "geometry" / "hermite.py").write_text("from .. import __version__\nfrom . import coords\n")
    (package / "apps" / "cli.py").write_text("from ..geometry import coords\n")
    assert offences(import_graph(package)) == ["spheroseg.geometry.coords imports spheroseg.apps.cli (line 2)",
                                               "spheroseg.geometry.hermite imports spheroseg (line 1)"]


def test_the_top_holds_only_the_folders_and_four_modules():
    assert sorted(p.stem for p in PACKAGE.glob("*.py")) == sorted(TOP)
    assert sorted(p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__") == sorted(LAYERS)


def test_the_folders_stand_on_at_most_eight_floors():
    graph = import_graph()
    above = {f: set() for f in LAYERS}
    for module, edges in graph.items():
        for target in edges:
            if folder(module) and folder(target) and folder(target) != folder(module):
                above[folder(module)].add(folder(target))

    def floor(f):
        return 1 + max((floor(g) for g in above[f]), default=0)

    assert max(map(floor, LAYERS)) <= 8


def test_no_module_reaches_the_package_init():
    # ``from . import __version__`` would load every front end (batch, io)
    graph = import_graph()
    assert [m for m, edges in graph.items() if "spheroseg" in edges and m != "spheroseg.__main__"] == []


def test_the_method_never_imports_the_synthetic_data():
    # the phantom is the ground truth the method is measured on, not a part of
    # it: only the demo's front ends reach it
    graph = import_graph()
    users = sorted(m for m, edges in graph.items() if not m.startswith("spheroseg.synthetic")
                   and any(t.startswith("spheroseg.synthetic") for t in edges))
    assert users == ["spheroseg.apps.batch", "spheroseg.apps.cli"]


def test_every_old_module_path_is_a_deprecated_alias_of_the_new_one():
    # in a fresh interpreter: each old path imported for the first time warns
    # once, naming the new path, and is the new module itself
    code = """
import importlib, importlib.util, json, sys, warnings
import spheroseg
from spheroseg._moved import MOVED
found = {}
for old in sorted(MOVED):
    if importlib.util.find_spec("spheroseg." + MOVED[old]) is None:  # the kernels, not built: no alias to test
        continue
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module("spheroseg." + old)
    found[old] = [module is importlib.import_module("spheroseg." + MOVED[old]),
                  [str(w.message) for w in caught if w.category is DeprecationWarning]]
found["segment is the function"] = callable(spheroseg.segment) and callable(spheroseg.locate)
print(json.dumps(found))
"""
    env = dict(os.environ, PYTHONPATH=SUBPROCESS_PATH)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    found = json.loads(out.stdout.strip().splitlines()[-1])
    from spheroseg._moved import MOVED

    assert found.pop("segment is the function") is True
    from importlib.util import find_spec

    assert found == {old: [True, [f"spheroseg.{old} moved to spheroseg.{new} in spheroseg 0.2.0; the old path "
                                  "goes in 0.3.0"]] for old, new in MOVED.items() if find_spec(f"spheroseg.{new}")}


def test_an_old_submodule_path_is_not_loaded_twice():
    # spheroseg.viewer.session must be the module of its new path, not a
    # second copy found in the folder its parent's alias stands for
    import importlib
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        old = importlib.import_module("spheroseg.viewer.session")
    assert old is importlib.import_module("spheroseg.apps.viewer.session")
