"""A griffe extension for the docs site (mkdocs.yml): the docstrings' Sphinx roles as code.

The docstrings are Google style with reST cross-reference roles (``:class:`~c3bf_gym.x.Y```),
which Markdown would print literally. This turns each role into inline code: ``~a.b.C`` shows as
``C``, ``a.b.C`` as ``a.b.C``, ``.robot`` (relative) as ``robot``. A paragraph ending in the reST
literal-block marker ``::`` ends in ``:`` (the indented block after it is already a Markdown code
block). Loaded by mkdocstrings only; the package does not import it.
"""

from __future__ import annotations

import re

import griffe

_LITERAL = re.compile(r"(?<=\S)::$", re.M)
_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|mod|data|obj|exc|const):`(~?)\.?([^`]+)`")


def _code(match: re.Match) -> str:
    short, target = match.group(1), match.group(2)
    return f"`{target.rsplit('.', 1)[-1] if short else target}`"


class SphinxRoles(griffe.Extension):
    """Rewrite ``:role:`target``` in every docstring to Markdown inline code."""

    def on_object(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and ":" in obj.docstring.value:
            obj.docstring.value = _LITERAL.sub(":", _ROLE.sub(_code, obj.docstring.value))
