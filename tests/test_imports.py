"""What importing spheroseg costs: neither numba nor matplotlib until used."""

import json
import os
import subprocess
import sys
from pathlib import Path


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
