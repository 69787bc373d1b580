"""Sphinx extension: read crater_thermal's docstrings as they are written, and resolve their short references.

The docstrings are numpy-style and written to be read in a terminal as much as in a browser, with
plain-text mathematics. Three of their habits are not reStructuredText; this extension translates them
after numpydoc has run (``autodoc-process-docstring``), so the build stays strict (``-W -n``) without
rewriting the code's text:

* ``|x|`` is an absolute value, never an RST substitution (the package defines none): the bars are
  escaped outside inline literals and roles.
* A section underline or a simple-table border shorter than its text is lengthened to fit it.
* A section heading numpydoc does not know (which it would drop, content and all) is renamed to the
  standard section of :data:`SECTION_ALIASES`.

The last rule acts on the raw docstring, before numpydoc; the others on numpydoc's output.

References (``missing-reference``): a short name such as ``ConfigError`` or ``materials.PropertySet`` is
linked to the one documented crater_thermal object whose full name ends with it. A reference to an
object that exists in the code but has no entry in the reference (a private helper, an undocumented
constant) is shown as code, unlinked. A reference to a name that does not exist stays a warning, so a
stale docstring still fails the build.
"""

from __future__ import annotations

import importlib
import re

#: Section headings numpydoc does not know, and the standard section each one is shown as.
SECTION_ALIASES = {
    "Fields (from :data:`SCHEMA`)": "Attributes",  # the case sections' fields, appended by config._section
}


_INLINE = re.compile(r"``.*?``|:[a-z:]+:`[^`]*`|`[^`]*`_?")
_ABS = re.compile(r"(?<![\\|])\|(?=\S)([^|\n]*?\S)\|(?!\|)")
_UNDERLINE = re.compile(r"^\s*([=\-~^])\1{2,}\s*$")
_BORDER = re.compile(r"^(\s*)(=+)( +=+)+\s*$")


def _escape_abs(line: str) -> str:
    out, last = [], 0
    for m in _INLINE.finditer(line):
        out.append(_ABS.sub(r"\\|\1\\|", line[last : m.start()]))
        out.append(m.group(0))
        last = m.end()
    out.append(_ABS.sub(r"\\|\1\\|", line[last:]))
    return "".join(out)


def _fix_underlines(lines: list[str]) -> None:
    for i in range(1, len(lines)):
        under, title = lines[i], lines[i - 1]
        if not title.strip() or not _UNDERLINE.match(under) or _UNDERLINE.match(title):
            continue
        if i >= 2 and lines[i - 2].strip():
            continue  # a title follows a blank line
        if len(under.strip()) < len(title.strip()):
            indent = len(under) - len(under.lstrip())
            lines[i] = " " * indent + under.strip()[0] * len(title.strip())


def _fix_simple_tables(lines: list[str]) -> None:
    i = 0
    while i < len(lines):
        if not _BORDER.match(lines[i]):
            i += 1
            continue
        j = i + 1
        while j < len(lines) and lines[j].strip():
            j += 1
        block = range(i, j)  # the table: from its top border to the blank line after it
        spans = [[m.start(), m.end()] for m in re.finditer(r"=+", lines[i])]
        for k in block:
            if _BORDER.match(lines[k]):
                continue
            for c, (_start, b) in enumerate(spans):
                limit = spans[c + 1][0] - 1 if c + 1 < len(spans) else None
                end = b
                while end < len(lines[k]) and lines[k][end] != " " and (limit is None or end < limit):
                    end += 1
                spans[c][1] = max(b, end)
        for k in block:
            if _BORDER.match(lines[k]):
                indent = lines[k][: len(lines[k]) - len(lines[k].lstrip())]
                row = list(" " * (spans[-1][1]))
                for a, b in spans:
                    row[a:b] = "=" * (b - a)
                lines[k] = (indent + "".join(row)[len(indent) :]).rstrip()
        i = j


def _before_numpydoc(app, what, name, obj, options, lines) -> None:
    """On the raw docstring: section aliases."""
    for i in range(len(lines) - 1):
        title = lines[i].strip()
        if title in SECTION_ALIASES and _UNDERLINE.match(lines[i + 1]):
            indent = lines[i][: len(lines[i]) - len(lines[i].lstrip())]
            lines[i] = indent + SECTION_ALIASES[title]
            lines[i + 1] = indent + "-" * len(SECTION_ALIASES[title])


def _after_numpydoc(app, what, name, obj, options, lines) -> None:
    """On numpydoc's reStructuredText: absolute values, underlines, simple tables."""
    lines[:] = [_escape_abs(line) for line in lines]
    _fix_underlines(lines)
    _fix_simple_tables(lines)


def _exists(dotted: str) -> bool:
    """Whether ``dotted`` names a module or an attribute of one (imported, not documented)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except Exception:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def _missing_reference(app, env, node, contnode):
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"].lstrip("~.")
    module = node.get("py:module") or ""
    cls = node.get("py:class") or ""
    domain = env.get_domain("py")
    # 1. the one documented crater_thermal object whose full name ends with the target
    matches = [
        full
        for full in domain.objects
        if full.startswith("crater_thermal.") and (full == target or full.endswith("." + target))
    ]
    if len(matches) == 1:
        entry = domain.objects[matches[0]]
        from sphinx.util.nodes import make_refnode

        return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, matches[0])
    if len(matches) > 1:
        return None  # ambiguous: Sphinx's own warning stands
    # 2. an object of the code without an entry: shown as code, not linked
    scopes = [f"{module}.{cls}" if cls else "", module, "crater_thermal", ""]
    for scope in scopes:
        full = f"{scope}.{target}" if scope else target
        if full.startswith("crater_thermal") and _exists(full):
            return contnode
    return None


def setup(app):
    app.connect("autodoc-process-docstring", _before_numpydoc, priority=100)  # numpydoc's is 500
    app.connect("autodoc-process-docstring", _after_numpydoc, priority=900)
    app.connect("missing-reference", _missing_reference)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
