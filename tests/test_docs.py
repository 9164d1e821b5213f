"""The documentation's promises: every Python block of the user guide (docs/guide/*.md) runs
as written, and nothing a user reads points at a file they do not have (API.md). The docs
build itself (Sphinx, warnings as errors) is part of scripts/test.sh (scripts/docs.sh)."""

import re
from pathlib import Path

import pytest

import kinema as km

ROOT = Path(__file__).resolve().parents[1]
GUIDE = sorted((ROOT / "docs" / "guide").glob("*.md"))
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)

pytestmark = pytest.mark.skipif(not GUIDE, reason="no docs/ beside the tests")


@pytest.mark.parametrize("page", GUIDE, ids=[p.stem for p in GUIDE])
def test_guide_examples_run(page, tmp_path, monkeypatch, capsys):
    blocks = BLOCK.findall(page.read_text())
    if page.stem in ("smoke", "sph", "cloth", "softbody", "fmm", "poisson", "io"):
        assert blocks, f"{page.name} has no quick start"
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for code in blocks:
        exec(compile(code, str(page), "exec"), namespace)  # noqa: S102 -- the guide's own examples
    capsys.readouterr()


def test_nothing_points_at_missing_files():
    texts = {"km.__doc__": km.__doc__}
    for path in Path(km.__file__).parent.rglob("*.py"):  # the docstrings help() shows
        texts[str(path)] = path.read_text()
    for path in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        texts[str(path.relative_to(ROOT))] = path.read_text()
    for name, text in texts.items():
        assert "API.md" not in text, name
    readme = texts["README.md"]
    assert readme.count("```") % 2 == 0 and "as they land" not in readme
    # Every relative link of the README leads to a file of the repository.
    for target in re.findall(r"\]\(([^)#:]+)\)", readme):
        assert (ROOT / target).exists(), target
