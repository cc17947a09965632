"""The documentation site (mkdocs.yml, docs/): every public name has an API entry and every
entry names something public; the README sections and anchors the site is made of exist. The
build itself (mkdocs build --strict) and its search index need the docs extra: marked `docs`."""

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import jaxgeom

ROOT = Path(__file__).parents[1]
DOCS = ROOT / "docs"


def public_names() -> set[str]:
    init = (ROOT / "jaxgeom" / "__init__.py").read_text()
    return set(re.findall(r"^from \.[\w.]+ import (\w+) as \1$", init, flags=re.M))


def documented() -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for page in sorted((DOCS / "api").glob("*.md")):
        for name in re.findall(r"^::: jaxgeom\.(\w+)$", page.read_text(), flags=re.M):
            found.setdefault(name, []).append(page.name)
    return found


def hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_public_name_has_one_api_entry():
    entries = documented()
    missing = sorted(public_names() - set(entries))
    assert not missing, f"add `::: jaxgeom.NAME` to a page of docs/api/ for {missing}"
    twice = {name: pages for name, pages in entries.items() if len(pages) > 1}
    assert not twice, twice


def test_every_api_entry_names_something_public():
    stale = sorted(name for name in documented() if name not in public_names() or not hasattr(jaxgeom, name))
    assert not stale, f"docs/api/ documents names jaxgeom no longer exports: {stale}"


def test_every_readme_section_and_anchor_the_site_uses_exists():
    h = hooks()
    readme = (ROOT / "README.md").read_text()
    for page in DOCS.rglob("*.md"):
        for title in re.findall(r"<!-- readme: (.+?) -->", page.read_text()):
            assert f"\n## {title}\n" in readme, f"{page}: the README has no section {title!r}"
            h.relative_links(h.readme_section(title), str(page.relative_to(DOCS)))  # every anchor has a page
    for target in set(h.PAGES.values()):
        assert (DOCS / target).is_file(), target


@pytest.mark.docs
def test_the_site_builds_strictly_and_search_finds_the_kernels(tmp_path):
    if shutil.which("mkdocs") is None and importlib.util.find_spec("mkdocs") is None:
        pytest.skip('the docs extra is not installed: pip install -e ".[docs]"')
    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    )
    docs = json.loads((site / "search" / "search_index.json").read_text())["docs"]

    def found(location: str, word: str) -> bool:
        return any(location in d["location"] and word in (d["title"] + d["text"]).lower() for d in docs)

    assert found("#jaxgeom.ricci_scalar", "curvature")
    assert found("#jaxgeom.delaunay", "periodic")
    for page in ("cli/", "notebooks/08_trajectories/", "bench/"):
        assert any(d["location"].startswith(page) for d in docs), page
    # formulas are MathML in the pages (docs/hooks.py), none left as TeX for a script to render
    pages = {p: p.read_text() for p in site.rglob("*.html")}
    assert not [p for p, text in pages.items() if 'class="arithmatex"' in text]
    curvature = pages[site / "api" / "curvature" / "index.html"]
    assert curvature.count('display="block"') >= 2 and "<mfrac>" in curvature
    # the docstrings' formulas too: ricci_scalar's entry states R_i as MathML
    entry = curvature[curvature.index('id="jaxgeom.ricci_scalar"') :]
    assert "<math" in entry[: entry.index("Source code")]
    # the notebooks' pages show what the notebook tier executed (docs/hooks.py), or say they do not
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        page = pages[site / "notebooks" / notebook.stem / "index.html"]
        if os.environ.get("JAXGEOM_EXECUTED_NOTEBOOKS"):
            assert "data:image/png;base64" in page and "Shown without outputs" not in page, notebook.name
        else:
            assert "Shown without outputs" in page, notebook.name


def test_the_site_refuses_a_stale_executed_notebook(tmp_path, monkeypatch):
    """An executed copy whose cells differ from the committed notebook's is refused, so the site
    cannot show outputs of code it no longer holds."""
    committed = json.loads((ROOT / "notebooks" / "01_tessellation.ipynb").read_text())
    monkeypatch.setenv("JAXGEOM_EXECUTED_NOTEBOOKS", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="pytest -m notebooks"):
        hooks().executed_copy("01_tessellation.ipynb", committed)
    edited = json.loads(json.dumps(committed))
    edited["cells"][-1]["source"] = ["print('changed')"]
    (tmp_path / "01_tessellation.ipynb").write_text(json.dumps(edited))
    with pytest.raises(ValueError, match="stale"):
        hooks().executed_copy("01_tessellation.ipynb", committed)
    (tmp_path / "01_tessellation.ipynb").write_text(json.dumps(committed))
    assert hooks().executed_copy("01_tessellation.ipynb", committed) == committed


def docs_code_blocks() -> list[tuple[str, str]]:
    """(page, code) of every Python block written in docs/ itself (the README's, which the
    guides include, run in tests/test_readme.py)."""
    blocks = []
    for page in sorted(DOCS.rglob("*.md")):
        for code in re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S):
            blocks.append((str(page.relative_to(DOCS)), code))
    return blocks


@pytest.mark.parametrize("page, code", docs_code_blocks(), ids=lambda v: v if v.endswith(".md") else "")
def test_every_code_block_of_the_docs_runs(page, code):
    exec(compile(code, f"docs/{page}", "exec"), {})
