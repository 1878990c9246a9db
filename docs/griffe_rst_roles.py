"""Griffe extension for the API page: reStructuredText roles in docstrings as code.

The docstrings are numpydoc with Sphinx roles (``:func:`sffscan.scan```); mkdocstrings
renders Markdown, where a role would show as raw text. Each role becomes inline code.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|exc|obj|const|ref):`~?([^`]+)`")


class RstRoles(griffe.Extension):
    """Replace ``:role:`target``` by ``target`` in inline code, in every docstring."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(r"`\1`", obj.docstring.value)
