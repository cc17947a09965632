"""mkdocs hooks: pages made of the README's sections (its links rewritten for the site), and the
command line page from the argparse parsers, so neither can drift from its source."""

import contextlib
import html as htmllib
import io
import re
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
