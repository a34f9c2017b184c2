"""The toolkit parts teach by example: their docstrings carry doctests, and the test run runs them."""

from __future__ import annotations

import configparser
import doctest
import importlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODULES = ("cameras", "rays", "pose", "samplers", "compositor", "encodings", "renderer")


def _doctests(name: str) -> list[doctest.DocTest]:
    module = importlib.import_module(f"adnerf.{name}")
    return [t for t in doctest.DocTestFinder().find(module) if t.examples]


def test_the_toolkit_parts_carry_at_least_fifteen_doctests() -> None:
    counts = {name: len(_doctests(name)) for name in MODULES}
    assert all(counts.values()), f"a toolkit module without an example: {counts}"
    assert sum(counts.values()) >= 15, counts


def test_the_test_run_collects_them() -> None:
    """setup.cfg's pytest section runs the doctests of every toolkit module (``--doctest-modules``)."""
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    section = cfg["tool:pytest"]
    assert "--doctest-modules" in section["addopts"].split()
    paths = section["testpaths"].split()
    missing = [name for name in MODULES if f"src/adnerf/{name}.py" not in paths]
    assert not missing, f"toolkit modules whose doctests the test run skips: {missing}"
