"""griffe extension (mkdocstrings): the docstrings' Sphinx cross-reference roles (``:meth:`X```,
``:class:`~a.b.C```) written as what Markdown shows them as — inline code of the name as the role
would display it — so that the API pages carry no raw role. Configured in ``mkdocs.yml``."""

from __future__ import annotations

import re
from typing import Any

import griffe

#: a role, its optional ``~`` (show the last component only) and its target
ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|attr|data|exc|obj|const|ref|doc):`(~?)([^`]+)`")


def plain(text: str) -> str:
    """``text`` with every Sphinx role replaced by inline code of the name it displays."""
    def shown(m: re.Match[str]) -> str:
        target = m.group(2).strip()
        label = re.match(r"(.*?)\s*<(.+)>$", target)  # :ref:`text <target>`
        name = label.group(1) if label else target
        return f"`{name.rsplit('.', 1)[-1] if m.group(1) else name}`"

    return ROLE.sub(shown, text)


class SphinxRoles(griffe.Extension):
    """Rewrite each loaded object's docstring through :func:`plain`."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain(obj.docstring.value)
