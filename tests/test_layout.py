"""The package's rooms: the public entry points stay where users import them from, and the layers
of the code import only downward: toolkit < audio < model < synth < preprocess < evaluation <
commands < bench < cli. Every room is covered; an import that runs back up or across fails."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import adnerf

PACKAGE = Path(adnerf.__file__).parent

# The toolkit parts a researcher composes, and the small utilities beside them (adnerf/*.py).
TOOLKIT = {"rays", "cameras", "pose", "samplers", "rng", "occupancy", "encodings", "fields", "compositor", "renderer", "analytic", "metrics", "io", "atomic", "outputs", "allocator", "memory", "lock", "ridge", "threads"}
# What each room may import besides itself and the toolkit: the rooms below it.
FLOORS = ["audio", "model", "synth", "preprocess", "evaluation", "commands", "bench", "cli"]
MAY_IMPORT = {room: set(FLOORS[:k]) for k, room in enumerate(FLOORS)}
MAY_IMPORT["__init__"] = {"model"}  # the package re-exports the layer and its condition


def _imports(source: str, module: str) -> set[str]:
    """The adnerf modules that the source of ``module`` (dotted, e.g. ``adnerf.model.train``;
    a package as ``adnerf.model.__init__``) imports, relative imports resolved."""
    package = module.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                out.add(".".join(base + ([node.module] if node.module else [])))
            elif node.module and node.module.startswith("adnerf"):
                out.add(node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("adnerf")}
    return out


def _room(module: str) -> str:
    """``adnerf.model.train`` -> ``model``; ``adnerf.cameras`` -> ``cameras``."""
    return module.split(".")[1] if module.count(".") else ""


def test_the_public_entry_points_import_from_where_users_import_them() -> None:
    from adnerf.cameras import pixel_rays
    from adnerf.cli import main
    from adnerf.compositor import composite, render_weights
    from adnerf.pose import from_canonical, to_canonical
    from adnerf.samplers import sample_pdf

    assert all(callable(f) for f in (pixel_rays, main, composite, render_weights, from_canonical, to_canonical, sample_pdf))
    from adnerf.audio import AudioAttNet, AudioNet  # the audio room re-exports its networks

    assert AudioNet.__module__ == "adnerf.audio.nets" and AudioAttNet.__module__ == "adnerf.audio.nets"


@pytest.mark.parametrize("room", ["audio", "model", "evaluation", "commands", "bench", "preprocess"])
def test_every_module_of_a_room_imports(room: str) -> None:
    for path in sorted((PACKAGE / room).glob("*.py")):
        name = f"adnerf.{room}" + ("" if path.stem == "__init__" else f".{path.stem}")
        assert importlib.import_module(name) is not None


def test_the_layers_of_the_code_import_only_downward() -> None:
    found = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__", "cli", "synth"}
    assert found == TOOLKIT, "a new top-level module: put it in a room, or name it a toolkit part here"
    rooms = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert rooms <= set(MAY_IMPORT), f"a room the import rule does not cover: {sorted(rooms - set(MAY_IMPORT))}"
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        room = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        allowed = TOOLKIT if room in TOOLKIT else TOOLKIT | MAY_IMPORT[room] | {room}
        module = ".".join(("adnerf",) + rel.with_suffix("").parts)
        for target in _imports(path.read_text(), module):
            if target.startswith("adnerf.") and _room(target) not in allowed:
                wrong.append(f"{rel} imports {target}")
    assert not wrong, wrong


def test_the_import_rule_resolves_relative_imports() -> None:
    """A toolkit module reaching up into the model is seen as importing the model room."""
    assert _imports("from .model.train import train\nfrom . import cameras\n", "adnerf.pose") == {"adnerf.model.train", "adnerf"}
    assert _imports("from ..fields import F\nfrom .data import D\nimport adnerf.io\n", "adnerf.model.layers") == {"adnerf.fields", "adnerf.model.data", "adnerf.io"}
    assert _room("adnerf.model.train") == "model" and _room("adnerf.cameras") == "cameras"
