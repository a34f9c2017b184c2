"""The docs stay true: the README is a short guide whose example runs, every results page is what
tools/make_docs.py makes from docs/bench/, and every local link points at a file."""

from __future__ import annotations

import ast
import importlib.util
import io
import json
import re
import shutil
import tokenize
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _make_docs(root: Path = ROOT) -> ModuleType:
    """tools/make_docs.py as a module, reading and writing under ``root``."""
    spec = importlib.util.spec_from_file_location("make_docs", ROOT / "tools" / "make_docs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.ROOT, module.BENCH = root, root / "docs" / "bench"
    module.PAGE, module.README = root / "docs" / "benchmarks.md", root / "README.md"
    return module


def test_the_committed_pages_are_what_the_script_makes() -> None:
    make_docs = _make_docs()
    assert (ROOT / "docs" / "benchmarks.md").read_text() == make_docs.make_page(), "docs/benchmarks.md is stale: python tools/make_docs.py"
    assert README.read_text() == make_docs.make_readme(README.read_text()), "README.md's results are stale: python tools/make_docs.py"
    assert make_docs.main(["--check"]) == 0


def test_a_result_edited_without_regenerating_is_caught(tmp_path: Path) -> None:
    """Change one number in a copy of docs/bench: the check fails, and regenerating shows the new number."""
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copy(README, tmp_path / "README.md")
    make_docs = _make_docs(tmp_path)
    assert make_docs.main(["--check"]) == 0
    path = tmp_path / "docs" / "bench" / "real_minute_512.json"
    doc = json.loads(path.read_text())
    doc["features"]["row"]["lmd_mouth_px"] = 1.2345  # the default's 512 px run, in the README's table too
    path.write_text(json.dumps(doc))
    assert make_docs.main(["--check"]) == 1
    assert make_docs.main([]) == 0
    assert "1.23" in (tmp_path / "docs" / "benchmarks.md").read_text()
    assert "LMD 1.23 px" in (tmp_path / "README.md").read_text()
    assert make_docs.main(["--check"]) == 0


def test_the_amplitude_table_reads_a_shrunk_opening() -> None:
    """A render whose opening is the truth's, shrunk about its mean by 0.5 and moved down 1 px,
    reads correlation 1, std ratio and slope 0.5, gap -1 px; stretched back to slope 0.8 its
    deviations are 0.8 of the truth's, so its RMSE is that of 0.2 of them, 1 px down."""
    make_docs = _make_docs()
    true = [0.0, 2.0, 4.0, 10.0, 6.0, 3.0]
    mean = sum(true) / len(true)
    render = [mean - 1.0 + 0.5 * (t - mean) for t in true]
    corr, square, std_ratio, slope, gap, rmse, stretch = make_docs.opening_amplitude({"mouth_opening_true_px": true, "mouth_opening_render_px": render})
    assert (corr, square, std_ratio, slope, gap) == ("1.00", "1.00", "0.50", "0.50", "-1.00")
    sd = (sum((t - mean) ** 2 for t in true) / len(true)) ** 0.5
    assert rmse == f"{(1 + (0.5 * sd) ** 2) ** 0.5:.2f}"
    assert stretch == f"1.60 / {(1 + (0.2 * sd) ** 2) ** 0.5:.2f}"


def test_the_readme_is_a_short_guide() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; move detail into docs/"
    first_picture = next(i for i, line in enumerate(lines) if line.startswith("!["))
    assert first_picture < 40
    # The two commands, unchanged.
    text = "\n".join(lines)
    assert '```bash\npip install -e ".[dev]" && adnerf demo\n```' in text
    assert "```bash\npytest\n```" in text


def test_the_readme_example_runs() -> None:
    """The 'Compose the parts' example runs as written and renders the product's layer class."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert len(blocks) == 1
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102 - our own README
    from adnerf.model.layers import RadianceLayer

    assert isinstance(namespace["head"], RadianceLayer)
    assert tuple(namespace["image"].shape) == (64, 64, 3)
    assert float(namespace["out"].opacity.max()) > 0


@pytest.mark.parametrize("page", [README, *sorted((ROOT / "docs").glob("*.md"))], ids=lambda p: p.name)
def test_local_links_point_at_files(page: Path) -> None:
    missing = []
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
        if "://" in target:
            continue
        if not (page.parent / target).exists():
            missing.append(target)
    assert not missing, f"{page.name} links to missing files: {missing}"


def _comments_and_docstrings(path: Path) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment and docstring of a Python file."""
    source = path.read_text()
    out = [(t.start[0], t.string) for t in tokenize.generate_tokens(io.StringIO(source).readline) if t.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                first = node.body[0].lineno
                out += [(first + k, line) for k, line in enumerate(doc.splitlines())]
    return out


def test_no_source_comment_tells_an_earlier_versions_figures() -> None:
    """Docstrings and comments say what the code is; measurement history lives in docs/decisions.md."""
    pattern = re.compile(r"earlier version|previous version|this version|was [0-9.]+ ?dB|[0-9.]+ -> [0-9.]+ ?dB|(rose|fell) from [0-9.]+ to", re.I)
    hits = [
        f"{path.relative_to(ROOT)}:{n}: {text.strip()[:80]}"
        for path in sorted((ROOT / "src" / "adnerf").rglob("*.py"))
        for n, text in _comments_and_docstrings(path)
        if pattern.search(text)
    ]
    assert not hits, "\n".join(hits)


def test_the_history_check_sees_comments_and_docstrings(tmp_path: Path) -> None:
    path = tmp_path / "m.py"
    path.write_text('"""Module.\n\nThe previous version scored less."""\n\nx = 1  # the head rose from 30.1 to 31.2 dB\ny = "this version is a string, not a docstring"\n')
    found = [text for _, text in _comments_and_docstrings(path)]
    assert any("previous version" in t for t in found) and any("rose from" in t for t in found)
    assert not any("a string, not" in t for t in found)
