"""mkdocs hooks: pages made of the README's sections (its links rewritten for the site), the
command line page from the argparse parsers, so neither can drift from its source, and the
notebooks' pages from the copies the notebook tier executed."""

import contextlib
import html as htmllib
import io
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

ROOT = Path(__file__).parents[1]
CLI_MARKER = "<!-- cli-help -->"
README_MARKER = re.compile(r"<!-- readme: (.+?) -->")
# where each README section lives on the site (its anchors point there)
PAGES = {
    "quick-tour": "getting-started.md",
    "geometry-of-your-own-points": "guides/own-points.md",
    "a-swarm": "guides/swarm.md",
    "tuning-by-gradient": "guides/tuning.md",
    "curvature-in-any-dimension": "guides/curvature-any-d.md",
    "scutoids-and-voronoi-facets": "guides/scutoids.md",
    "recorded-trajectories": "guides/trajectories.md",
    "several-devices": "guides/devices.md",
    "the-command-line": "cli.md",
    "gpus-triangulators-and-jax-versions": "guides/gpus.md",
    "how-the-graph-is-represented": "guides/graph.md",
    "architecture": "development.md",
    "development": "development.md",
}


def readme_section(title: str) -> str:
    """The body of the README's `## title` section."""
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}\n") + len(f"\n## {title}\n")
    end = text.find("\n## ", start)
    return text[start : end if end >= 0 else len(text)].strip() + "\n"


def relative_links(markdown: str, page: str) -> str:
    """README-relative links made relative to `page` (notebooks, bench/README.md, sections)."""
    up = "../" * page.count("/")

    def anchor(match):
        target = PAGES.get(match.group(1))
        if target is None:
            raise KeyError(f"README anchor #{match.group(1)} has no page on the site (docs/hooks.py PAGES)")
        return f"]({up}{target})"

    markdown = re.sub(r"\]\(#([a-z0-9-]+)\)", anchor, markdown)
    markdown = markdown.replace("](notebooks/", f"]({up}notebooks/")
    return markdown.replace("](bench/results/simulate/swarm.png)", f"]({up}images/swarm.png)")


def _help(command: str) -> str:
    from jaxgeom.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main([command, "--help"])
    return out.getvalue()


def on_page_markdown(markdown: str, page, **kwargs) -> str:
    markdown = README_MARKER.sub(lambda m: relative_links(readme_section(m.group(1)), page.file.src_uri), markdown)
    if CLI_MARKER in markdown:
        intro = relative_links(readme_section("The command line"), page.file.src_uri)
        blocks = [f"## jaxgeom {c}\n\n```text\n{_help(c)}```\n" for c in ("simulate", "analyze", "tune")]
        markdown = markdown.replace(CLI_MARKER, intro + "\n" + "\n".join(blocks))
    return markdown


ARITHMATEX = re.compile(r'<(span|div) class="arithmatex">\s*\\[(\[](.*?)\\[)\]]\s*</\1>', re.DOTALL)


def on_page_content(html: str, page, **kwargs) -> str:
    """Formulas as MathML (latex2mathml), which browsers render natively: no MathJax or KaTeX
    script, and nothing fetched from a CDN to build or to read the site."""
    from latex2mathml.converter import convert

    def mathml(m):
        display = "block" if m.group(1) == "div" else "inline"
        return convert(htmllib.unescape(m.group(2)).strip(), display=display)

    return ARITHMATEX.sub(mathml, html)


# The notebook tier (`pytest -m notebooks`, tests/apps/test_notebooks.py) writes the notebooks it
# executed here; the site shows their outputs, so the build never executes a notebook itself.
EXECUTED = "JAXGEOM_EXECUTED_NOTEBOOKS"
NO_OUTPUTS = (
    '!!! note "Shown without outputs"\n'
    "    This build of the site had no executed copy of the notebook. Run "
    "`JAXGEOM_EXECUTED_NOTEBOOKS=build/notebooks pytest -m notebooks`, then build with the same "
    "variable set, to show its outputs and figures."
)


def cell_sources(notebook: dict) -> list[tuple[str, str]]:
    """(type, source) of every cell: what an executed copy must share with the committed one."""
    return [(c["cell_type"], "".join(c["source"])) for c in notebook["cells"]]


def executed_copy(name: str, committed: dict) -> dict | None:
    """The notebook tier's executed copy of notebooks/`name`, refused when its cells differ from
    the committed notebook's (it was executed before the notebook changed)."""
    folder = os.environ.get(EXECUTED)
    if not folder:
        return None
    path = Path(folder) / name
    if not path.is_file():
        raise FileNotFoundError(f"{EXECUTED}={folder} has no executed {name}: run pytest -m notebooks with it set")
    executed = json.loads(path.read_text())
    if cell_sources(executed) != cell_sources(committed):
        raise ValueError(f"{path} is stale (its cells differ from notebooks/{name}): run pytest -m notebooks again")
    return executed


STAGING: list[Path] = []


def on_post_build(config, **kwargs):
    while STAGING:
        shutil.rmtree(STAGING.pop())


def on_files(files, config, **kwargs):
    """Each notebook page reads its executed copy, or the committed notebook under a note that
    says why no output is shown."""
    STAGING.append(Path(tempfile.mkdtemp(prefix="jaxgeom-docs-")))
    staging = STAGING[-1] / "notebooks"  # mkdocs-jupyter's include pattern matches notebooks/*.ipynb
    staging.mkdir()
    for file in files:
        if not (file.src_uri.startswith("notebooks/") and file.src_uri.endswith(".ipynb")):
            continue
        committed = json.loads(Path(file.abs_src_path).read_text())
        try:
            shown = executed_copy(Path(file.src_uri).name, committed)
        except (FileNotFoundError, ValueError) as error:
            from mkdocs.exceptions import PluginError

            raise PluginError(str(error)) from error  # mkdocs prints the message, no traceback
        if shown is None:
            note = {"cell_type": "markdown", "metadata": {}, "source": NO_OUTPUTS}
            shown = dict(committed, cells=[committed["cells"][0], note, *committed["cells"][1:]])
        target = staging / Path(file.src_uri).name
        target.write_text(json.dumps(shown))
        file.abs_src_path = str(target)
    return files
