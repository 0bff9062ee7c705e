"""What each setting of a settings class does: its attribute docstring (the string literal under
the field), read from the source when asked, not when the class is made.

Pydantic's ``use_attribute_docstrings`` parses every class's module when the class is created,
which made ``stereotrack methods`` pay for parsing a dozen modules; only ``methods NAME``, the
docs and the tests read the text, so they read it here."""

from __future__ import annotations

import ast
import inspect
import itertools
import textwrap
from functools import cache


@cache
def _own_docs(cls: type) -> dict[str, str]:
    """The attribute docstrings written in ``cls``'s own body (not its bases')."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # no source (a class made at run time): no docs
        return {}
    body = ast.parse(source).body[0]
    docs: dict[str, str] = {}
    stmts = getattr(body, "body", [])
    for stmt, nxt in itertools.pairwise(stmts):
        target = stmt.target if isinstance(stmt, ast.AnnAssign) else None
        if (isinstance(target, ast.Name) and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            docs[target.id] = inspect.cleandoc(nxt.value.value)
    return docs


def attribute_docs(cls: type) -> dict[str, str]:
    """Field name → its docstring, from ``cls`` and its bases (a subclass's own text wins)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is not object:
            docs.update(_own_docs(klass))
    return docs
