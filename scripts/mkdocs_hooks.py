"""MkDocs hook: docstrings use Sphinx roles (:func:`name`, :class:`Name`); mkdocstrings renders
the role's name as text in front of the code span. Drop the role, keep the code span."""

from __future__ import annotations

import re

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|attr|data|mod|obj|exc):(?=<code>)")


def on_page_content(html, **kwargs):
    return _ROLE.sub("", html)
