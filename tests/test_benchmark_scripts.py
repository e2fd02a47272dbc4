"""Every script in ``benchmarks/`` still imports against the current library and has a
``main``: the scripts are run by hand (and by a GPU session, with little time to spare), so
no other test notices when a refactor renames what they import."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(path.name for path in BENCHMARKS.glob("*.py"))
HELPERS = {"common.py"}  # imported by the scripts, not run


def test_the_scripts_are_found():
    assert {"device.py", "real_fibula.py", "plus_spine.py"} <= set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_benchmark_script_imports(script, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the scripts import their siblings
    name = f"benchmark_script_{Path(script).stem}"
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / script)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    assert module.__doc__, f"{script}: no docstring saying what it measures"
    if script not in HELPERS:
        assert callable(getattr(module, "main", None)), f"{script}: no main()"
