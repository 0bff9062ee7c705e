"""The documentation says one thing once: the site's home page is the README (links adjusted)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from tests.conftest import REPO


def test_docs_home_is_the_readme():
    readme = (REPO / "README.md").read_text()
    assert (REPO / "docs" / "index.md").read_text() == readme.replace("](docs/", "]("), \
        "docs/index.md drifted from README.md: regenerate it (README with '](docs/' → '](')"
    assert len(readme.splitlines()) <= 150


def test_file_formats_are_generated_from_the_schemas():
    """The Files page carries the generated tables: every schema's file and every column (runs of
    one meaning shown as ``first … last``) in order, and every output file."""
    import importlib.util

    from pipeline.core.clip import SCHEMAS
    from pipeline.core.outputs import Outputs
    from pipeline.present.summary import METHODS_SUMMARY, SUMMARY

    spec = importlib.util.spec_from_file_location("docs_hooks", REPO / "tools" / "docs_hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    page = (REPO / "docs" / "files.md").read_text()
    assert hooks.MARKER in page
    text = hooks.on_page_markdown(page)
    for schema in (*SCHEMAS, SUMMARY, METHODS_SUMMARY):
        section = text.split(f"### `{schema.file}`", 1)[1].split("###", 1)[0]
        rows = [r.split(" | ")[0].strip("| ") for r in section.splitlines() if r.startswith("| `")]
        shown = [n.strip("`") for r in rows for n in r.replace(" … ", ", ").split(", ")]
        own = list(schema.columns)
        assert shown[0] == own[0] and shown[-1] == own[-1] and set(shown) <= set(own), schema.file
        assert [n for n in own if n in shown] == shown, schema.file  # in order
    assert all(f"| `{f.name}` |" in text for f in Outputs.files())


@pytest.mark.slow
def test_built_site_shows_no_raw_sphinx_role(tmp_path):
    """The API pages render the docstrings' cross-reference roles (``:meth:`x```) as code: a strict
    build of the site holds no raw role on any page."""
    pytest.importorskip("mkdocs", reason="mkdocs comes with the docs extra (pip install -e '.[docs]')")
    site = tmp_path / "site"
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(site)], cwd=REPO,
                         capture_output=True, text=True, check=False, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert res.returncode == 0, res.stderr[-3000:]
    raw = re.compile(r":(?:py:)?(?:func|meth|class|mod|attr|data|exc|obj|const|ref):(?:<code>|`)")
    pages = sorted(site.rglob("*.html"))
    assert any("reference" in p.parts for p in pages)
    found = {str(p.relative_to(site)): len(raw.findall(p.read_text())) for p in pages}
    assert not {k: v for k, v in found.items() if v}, found
