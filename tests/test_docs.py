"""The documentation says one thing once: the site's home page is the README (links adjusted)."""

from __future__ import annotations

from tests.conftest import REPO


def test_docs_home_is_the_readme():
    readme = (REPO / "README.md").read_text()
    assert (REPO / "docs" / "index.md").read_text() == readme.replace("](docs/", "]("), \
        "docs/index.md drifted from README.md: regenerate it (README with '](docs/' → '](')"
    assert len(readme.splitlines()) <= 150
