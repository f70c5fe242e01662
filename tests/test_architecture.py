"""The layers hold: kernels import Warp and numpy only; every module imports on its own in a fresh
interpreter (no import cycles); the code is ruff-clean at line length 120."""
import ast
import pkgutil
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
KERNEL_IMPORTS_ALLOWED = {"warp", "numpy", "typing", "dataclasses", "__future__", "os", "concurrent", "math", "time",
                          "collections"}  # Warp and numpy; the rest is the standard library


def _modules() -> list[str]:
    import wrenorm
    import wrenorm.kernels
    import wrenorm.tasks
    import wrenorm.viz

    names = []
    for pkg in (wrenorm, wrenorm.kernels, wrenorm.tasks, wrenorm.viz):
        names.append(pkg.__name__)
        names += [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")]
    return sorted(set(n for n in names if not n.endswith("__main__")))


def test_kernels_import_warp_and_numpy_only():
    offenders = []
    for path in sorted((ROOT / "kernels").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for name in names:
                top = name.split(".")[0]
                if name.startswith("wrenorm."):
                    if not name.startswith("wrenorm.kernels"):
                        offenders.append(f"{path.relative_to(ROOT)} imports {name}")
                elif top not in KERNEL_IMPORTS_ALLOWED:
                    offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, offenders


def test_every_module_imports_alone_in_a_fresh_interpreter():
    """One fresh interpreter per module: an import cycle or a module that only works after another one was
    imported fails here."""
    mods = _modules()
    assert len(mods) > 40
    code = "import importlib, sys\nimportlib.import_module(sys.argv[1])\n"

    def check(m):
        proc = subprocess.run([sys.executable, "-c", code, m], capture_output=True, text=True, timeout=120)
        return None if proc.returncode == 0 else f"{m}: {(proc.stderr.strip().splitlines() or ['?'])[-1]}"

    with ThreadPoolExecutor(max_workers=2) as pool:
        failures = [f for f in pool.map(check, mods) if f]
    assert not failures, failures


def test_ruff_is_clean_at_line_length_120():
    ruff = shutil.which("ruff") or str(Path(sys.executable).parent / "ruff")
    if not Path(ruff).exists():
        pytest.fail("ruff is not installed (it is in the test extra: pip install -e '.[test]')")
    proc = subprocess.run([ruff, "check", "--output-format", "concise", str(ROOT)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:]
