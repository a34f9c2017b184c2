"""The package's rooms: the public entry points stay where users import them from, and the layers
of the code import only downward: toolkit < audio < formats < model < synth < preprocess < evaluation <
commands < bench < cli. Every room is covered; an import that runs back up or across fails."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import adnerf

PACKAGE = Path(adnerf.__file__).parent

# The toolkit parts a researcher composes, and the small utilities beside them (adnerf/*.py).
TOOLKIT = {"rays", "cameras", "pose", "samplers", "rng", "occupancy", "encodings", "fields", "compositor", "renderer", "analytic", "metrics", "io", "atomic", "allocator", "subnormals", "memory", "lock", "ridge", "threads"}
# What each room may import besides itself and the toolkit: the rooms below it.
FLOORS = ["audio", "formats", "model", "synth", "preprocess", "evaluation", "commands", "bench", "cli"]
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
    # The dataset module moved to the formats room; every name it had is still where it was.
    import adnerf.formats.dataset as dataset
    import adnerf.model.data as old_home

    had = ["EYE_CROP", "FORMAT", "LABEL_BACKGROUND", "LABEL_HEAD", "LABEL_TORSO", "MOUTH_CROP", "VERSION", "DatasetError", "SceneMeta", "TalkingHeadDataset", "Truth",
           "check_poses", "frame_bytes", "load_dataset", "read_meta", "save_dataset", "tail_split", "write_wav"]  # fmt: skip
    assert all(getattr(old_home, name) is getattr(dataset, name) for name in had)


@pytest.mark.parametrize("room", ["audio", "formats", "model", "evaluation", "commands", "bench", "preprocess"])
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


def _folder_names() -> tuple[set[str], set[str]]:
    """The file names of the dataset and run folders as the formats room spells them (files with
    a suffix; folders without), read from the naming classes themselves."""
    from adnerf.formats.dataset import TRUTH_FILES, DatasetFolder
    from adnerf.formats.run_folder import RunFolder

    paths = []
    for cls in (DatasetFolder, RunFolder):
        folder = cls(Path("ROOT"))
        paths += [getattr(folder, name) for name, member in vars(cls).items() if isinstance(member, property)]
    paths += [DatasetFolder(Path("ROOT")).frame(0), DatasetFolder(Path("ROOT")).labels(0)]
    paths += [DatasetFolder(Path("ROOT")).truth_file(k) for k in TRUTH_FILES]
    files = {p.name for p in paths if p.suffix and p.parent.name in ("ROOT", "truth")}
    folders = {p.name for p in paths if not p.suffix}
    return files, folders


def _spelled_names(source: str, files: set[str], folders: set[str]) -> list[str]:
    """Where ``source`` spells a folder file name in a string (docstrings aside): a string that
    holds one of ``files`` as a word, or a path joined with one of ``folders`` (``x / "frames"``)."""
    import re

    tree = ast.parse(source)
    docs = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                docs.add(id(first.value))
    word = re.compile(r"(?<![\w.])(" + "|".join(re.escape(f) for f in sorted(files)) + r")(?!\.?\w)")
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs and word.search(node.value):
            found.append(f"line {node.lineno}: {node.value[:60]!r}")
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and isinstance(node.right, ast.Constant) and node.right.value in folders:
            found.append(f"line {node.lineno}: / {node.right.value!r}")
    return sorted(found, key=lambda hit: int(hit.split(":")[0].split()[1]))


def test_only_the_formats_room_spells_the_folders_file_names() -> None:
    """``DatasetFolder`` and ``RunFolder`` own the names of every file of a dataset and a run
    folder: a module elsewhere that builds ``root / "poses.npy"`` or says ``no run.json`` would
    break when a name changes. The scan sees planted cases and passes names in docstrings and
    look-alikes (``poses.npy.bak``, ``my_meta.json``)."""
    files, folders = _folder_names()
    assert {"meta.json", "run.json", "checkpoint.pt", "log.jsonl", "poses.npy", "background.png", "landmarks.npy"} <= files
    assert {"frames", "parsing", "truth"} <= folders
    planted = 'def f(root):\n    """Reads root / "poses.npy" (a docstring may name it)."""\n    a = root / "poses.npy"\n    b = f"{root}: no run.json"\n    c = root / "frames"\n    d = "poses.npy.bak", "my_meta.json"\n'
    assert [s.split(":")[0] for s in _spelled_names(planted, files, folders)] == ["line 3", "line 4", "line 5"]
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "formats":
            continue
        wrong += [f"{rel} {hit}" for hit in _spelled_names(path.read_text(), files, folders)]
    assert not wrong, wrong


def _body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's lines from its first statement after the docstring to its end."""
    body = node.body
    if len(body) > 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
        body = body[1:]
    return node.end_lineno - body[0].lineno + 1  # type: ignore[operator]


def test_commands_are_short_parts_and_the_cli_a_list_of_them() -> None:
    """Each command is a ``register`` and a ``run``, and no function of a command or of
    preprocessing is longer than 60 lines (docstrings aside); ``cli.py`` lists the commands in at
    most 150 lines. The measure sees a planted long function."""
    long_one = "def f():\n    '''doc\n    more'''\n" + "    x = 1\n" * 61
    assert _body_lines(ast.parse(long_one).body[0]) == 61  # type: ignore[arg-type]
    assert len((PACKAGE / "cli.py").read_text().splitlines()) <= 150
    too_long = []
    for path in sorted((PACKAGE / "commands").glob("*.py")) + sorted((PACKAGE / "preprocess").glob("*.py")) + [PACKAGE / "cli.py", PACKAGE / "bench" / "command.py"]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _body_lines(node) > 60:
                too_long.append(f"{path.relative_to(PACKAGE)}: {node.name} ({_body_lines(node)} lines)")
    assert not too_long, too_long
    from adnerf import cli

    parts = [p for p in cli.COMMANDS if callable(getattr(p, "register", None))]
    assert len(parts) == len(cli.COMMANDS) == 12
    names = cli.build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    assert list(names) == ["bench", "features", "demo", "synth", "preprocess", "import-adnerf", "check-preprocess", "lip-signal", "train", "render", "stream", "evaluate"]
    assert all(names[n].get_default("func").__name__ == "run" for n in names if n != "bench")
