"""What each stage parameter means, for `stages --params`: the comments written beside its field.

A stage's params model documents its fields with comments in its source (the comment lines just
above a field and the one at the end of its line), where a maintainer reads them; this module
reads those comments back, so that the listing explains every parameter without a second copy
that could drift (21 of 158 parameters were documented nowhere else).
"""

from __future__ import annotations

import ast
import functools
import inspect
import io
import textwrap
import tokenize


def _comments_by_line(source: str) -> dict[int, str]:
    """{line number: comment text without '#'} of a piece of source."""
    out: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if text and not text.startswith(("fmt:", "noqa", "type:")):
                out[tok.start[0]] = text
    return out


@functools.cache  # a class's source is read and parsed once (a class per stage, many fields)
def _class_field_comments(cls: type) -> dict[str, str]:
    """{field: its comments} from the source of one class (not its bases)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # built dynamically, or no source on disk
        return {}
    comments = _comments_by_line(source)
    lines = source.splitlines()
    node = ast.parse(source).body[0]
    out: dict[str, str] = {}
    for stmt in getattr(node, "body", []):
        if not isinstance(stmt, ast.AnnAssign) or not isinstance(stmt.target, ast.Name):
            continue
        above, line = [], stmt.lineno - 1
        while line in comments and lines[line - 1].lstrip().startswith("#"):
            above.insert(0, comments[line])
            line -= 1
        # a field's own trailing comments (on its lines, a multi-line default included)
        own = [comments[n] for n in range(stmt.lineno, (stmt.end_lineno or stmt.lineno) + 1)
               if n in comments]  # fmt: skip
        text = " ".join(above + own).strip()
        if text:
            out[stmt.target.id] = text
    return out


def field_comments(model: type) -> dict[str, str]:
    """{field name: the comments beside it in the source} of a params model and its bases (a
    field redeclared in a subclass takes the subclass's comment)."""
    out: dict[str, str] = {}
    for cls in reversed(model.__mro__):
        if cls is object:
            continue
        out.update(_class_field_comments(cls))
    fields = getattr(model, "model_fields", None)
    return out if fields is None else {k: v for k, v in out.items() if k in fields}
