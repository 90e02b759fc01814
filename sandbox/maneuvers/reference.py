"""The maneuver reference (``docs/maneuvers.md``), generated from the maneuvers' own code.

Each parameter's text comes from its ``Params`` class: the ``Attributes:``
section of the docstring, or else the comment written on or just above the
field. Types and defaults come from the pydantic fields. Regenerate with::

    python -m sandbox.maneuvers.reference > docs/maneuvers.md

A test checks that the file is current and that every parameter has a text.
"""

from __future__ import annotations

import inspect
import io
import re
import tokenize
import typing

from pydantic_core import PydanticUndefined

HEADER = """# Maneuvers: every parameter

Generated from the maneuvers' code by `python -m sandbox.maneuvers.reference`;
do not edit by hand. Lengths are in m, speeds in m/s, angles in degrees,
forces in N, times in s unless a parameter says otherwise. How maneuvers
are written into a level's FSM, and macros: [levels.md](levels.md).
"""


def _docstring_attributes(cls: type) -> dict[str, str]:
    """``name: text`` entries of the ``Attributes:`` section of ``cls``'s own docstring."""
    doc = cls.__dict__.get("__doc__")
    if not doc:
        return {}
    lines = inspect.cleandoc(doc).split("\n")
    if "Attributes:" not in lines:
        return {}
    out: dict[str, str] = {}
    names: list[str] = []
    for line in lines[lines.index("Attributes:") + 1:]:
        entry = re.match(r"^    (\w[\w, ]*): (.*)$", line)  # a name right at the indent: not a continuation
        if entry:
            names = [n.strip() for n in entry.group(1).split(",")]
            for n in names:
                out[n] = entry.group(2).strip()
        elif line.startswith("        ") and names:
            for n in names:
                out[n] += " " + line.strip()
        elif line.strip():
            break
    return out


def _field_comments(cls: type) -> dict[str, str]:
    """Comments on a field's line, or in the block of comment lines just above it, in ``cls``'s source."""
    source = inspect.getsource(cls)
    out: dict[str, str] = {}
    block: list[str] = []
    pending: str | None = None
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if pending is not None:  # a comment after the field on its line
                out[pending] = text
                pending = None
            else:
                block.append(text)
        elif tok.type == tokenize.NAME and tok.start[1] == 4 and tok.line[4:].startswith(tok.string + ":"):
            if block:
                out[tok.string] = " ".join(block)
            block, pending = [], tok.string
        elif tok.type in (tokenize.NEWLINE, tokenize.NL):
            if tok.type == tokenize.NEWLINE:
                pending = None
            elif not tok.line.strip():
                block = []
    return out


def parameter_texts(params: type) -> dict[str, str]:
    """Parameter name -> its text ("" where none is written), docstrings first, then comments."""
    texts: dict[str, str] = {}
    for cls in reversed(params.__mro__):
        if cls.__module__.startswith("sandbox.maneuvers") and cls.__name__ != "Params":
            texts.update(_field_comments(cls))
            texts.update(_docstring_attributes(cls))
    return {name: texts.get(name, "") for name in params.model_fields}


_BOUNDS = (("gt", "> "), ("ge", ">= "), ("lt", "< "), ("le", "<= "), ("min_length", "length >= "),
           ("max_length", "length <= "))


def _type_text(tp) -> str:
    """A readable type: ``float (> 0)``, ``site``, ``list[site]``, ``Target | None``."""
    import types  # noqa: PLC0415

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Annotated:
        base, *meta = args
        if any(type(m).__name__ == "PlainValidator" for m in meta):
            return "site"  # a rope or cloth site (sandbox.model.sites)
        bounds = []
        for m in meta:
            for item in [m, *getattr(m, "metadata", [])]:
                for attr, sign in _BOUNDS:
                    if getattr(item, attr, None) is not None and type(item).__name__ != "FieldInfo":
                        bounds.append(f"{sign}{getattr(item, attr):g}")
        return _type_text(base) + (f" ({', '.join(bounds)})" if bounds else "")
    if origin in (typing.Union, types.UnionType):
        parts = [_type_text(a) for a in args if a is not type(None)]
        site = {"str", "int", "tuple[int, int]", "site"}
        if "site" in parts or {"str", "int"} <= set(parts):  # a rope or cloth site, maybe with literals
            parts = ["site"] + [q for q in parts if q not in site]
        return " | ".join(parts) + (" | None" if type(None) in args else "")
    if origin is typing.Literal:
        return " or ".join(repr(a) for a in args)
    if origin in (list, tuple):
        return f"{origin.__name__}[{', '.join(_type_text(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp))


def _default_text(field) -> str:
    if field.is_required():
        return "required"
    value = field.default if field.default is not PydanticUndefined else field.default_factory()
    return f"`{value!r}`"


def shipped(registry) -> list[tuple[str, type]]:
    """The maneuvers the sandbox ships (not those a host or a test registered), by name."""
    return sorted((n, c) for n, c in registry.items() if c.__module__.startswith("sandbox.maneuvers."))


def markdown() -> str:
    """The whole reference as Markdown."""
    import sandbox.maneuvers  # noqa: F401, PLC0415  (registers every maneuver)
    from sandbox.maneuvers.base import REGISTRY  # noqa: PLC0415

    out = [HEADER]
    for name, cls in shipped(REGISTRY):
        summary = inspect.cleandoc(cls.__doc__ or "").split("\n\n")[0].replace("\n", " ").replace("``", "`")
        out.append(f"\n## `{name}`\n\n{summary}\n")
        texts = parameter_texts(cls.Params)
        out.append("| parameter | type | default | what it does |\n|---|---|---|---|")
        hints = typing.get_type_hints(cls.Params, include_extras=True)
        for field_name, field in cls.Params.model_fields.items():
            kind = _type_text(hints.get(field_name, field.annotation)).replace("|", "\\|")
            text = " ".join(texts[field_name].split()).replace("|", "\\|").replace("``", "`")
            out.append(f"| `{field_name}` | {kind} | {_default_text(field)} | {text} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
