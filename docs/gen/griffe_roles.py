"""Griffe extension: Sphinx roles in the package's docstrings shown as code in the API pages.

The docstrings are Google style but name other objects as reST roles (:class:`~gpu_blur.Batch`,
:func:`synthesize`), which Markdown would show literally. Each becomes a code span of the name
as Sphinx would print it (the last part after ``~``). Double-colon literal blocks
(``Example::``) become fenced code.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj|const):`(~?)([^`]+)`")


def _role(m: re.Match) -> str:
    name = m.group(2)
    return f"`{name.rsplit('.', 1)[-1] if m.group(1) else name}`"


def _literal_blocks(text: str) -> str:
    """``Para::`` followed by an indented block: the paragraph, then the block fenced."""
    lines, out, i = text.splitlines(), [], 0
    while i < len(lines):
        line = lines[i]
        if line.rstrip().endswith("::") and not line.strip().startswith(".."):
            out.append(line.rstrip()[:-1] if not line.rstrip().endswith(" ::") else
                       line.rstrip()[:-3])
            i += 1
            block = []
            while i < len(lines) and (not lines[i].strip() or lines[i].startswith(" ")):
                block.append(lines[i])
                i += 1
            while block and not block[-1].strip():
                block.pop()
            indent = min((len(b) - len(b.lstrip()) for b in block if b.strip()), default=0)
            out += ["", "```python"] + [b[indent:] for b in block] + ["```", ""]
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


class SphinxRoles(griffe.Extension):
    """Rewrite each docstring once it is loaded."""

    def on_instance(self, *, obj, **kwargs) -> None:
        """The object's docstring, roles as code spans and literal blocks fenced."""
        doc = obj.docstring
        if doc is not None and not obj.is_alias:
            doc.value = _literal_blocks(ROLE.sub(_role, doc.value))
