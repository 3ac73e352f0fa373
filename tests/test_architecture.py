"""The architecture holds: import contracts, and a config that loads without the estimators.

The layers and contracts are declared once, in pyproject.toml (``[tool.importlinter]``);
these tests run import-linter on the real tree, show that it catches a forbidden import
added to a copy of the tree, and check that the wire-format layer and ``sinewatch config
show`` never load numba or an estimator module.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("schemas", "clients", "service")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint_imports(tree: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(tree / r) for r in ROOTS)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--config", str(tree / "pyproject.toml"), "--no-cache"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )


def test_the_import_contracts_hold():
    result = _lint_imports(REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


def test_a_forbidden_import_breaks_a_contract(tmp_path):
    for root in ROOTS:
        shutil.copytree(REPO / root, tmp_path / root, ignore=shutil.ignore_patterns("__pycache__", "json"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    codec = tmp_path / "schemas" / "sinewatch" / "schemas" / "codec.py"
    codec.write_text(codec.read_text() + "\nimport sinewatch.estimators  # a wire-format module reaching up\n")
    result = _lint_imports(tmp_path)
    assert result.returncode == 1
    assert "BROKEN" in result.stdout and "sinewatch.schemas.codec -> sinewatch.estimators" in result.stdout


def _modules_loaded_by(code: str) -> set[str]:
    probe = code + "\nimport sys\nprint('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, env={**os.environ})
    return set(out.stdout.split())


def test_validating_a_config_loads_no_estimator_and_no_numba(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[[rules]]\nmatch = "sinewatch/in/**"\nestimator = "ipdft"\nparams = { window_cycles = 4 }\n')
    loaded = _modules_loaded_by(f"from sinewatch.schemas.config import load_config; load_config({str(cfg)!r}, {{}})")
    assert "numba" not in loaded and "scipy" not in loaded and "zenoh" not in loaded
    assert not any(m.startswith("sinewatch.estimators") for m in loaded)


def test_config_show_loads_no_estimator_and_no_numba():
    loaded = _modules_loaded_by(
        "import contextlib, io\nfrom sinewatch.apps.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()): main(['config', 'show'])"
    )
    assert "numba" not in loaded and not any(m.startswith("sinewatch.estimators") for m in loaded)
