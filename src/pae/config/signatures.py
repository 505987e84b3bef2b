"""Config schemas read from the classes themselves: a constructor's keyword arguments (or a
settings dataclass's fields) with their annotations and defaults (literals, or module-level
constants holding one), parsed from the module's source with ``ast``. The module is not
imported, so a launching process makes the schemas of torch models without torch; the
class's signature stays the one home of its defaults."""

from __future__ import annotations

import ast
import dataclasses
import functools
from pathlib import Path
from typing import Any

from omegaconf import MISSING

PLAIN_TYPES = {"int": int, "float": float, "bool": bool, "str": str}
"""Annotations a schema types; any other is ``Any`` (checked by the class)."""
STEP_FILLED = ("n_scenes",)
"""Constructor arguments the steps fill in (the data's scene count): never configured."""
SOURCE_ROOT = Path(__file__).resolve().parents[1]
"""The folder of the ``pae`` package's modules."""


@functools.cache
def _module_tree(module: str) -> ast.Module:
    """The parsed source of ``module`` (``pae.<...>``; a package: its ``__init__.py``)."""
    parts = module.split(".")
    if parts[0] != "pae":
        raise ValueError(f"{module}: not a module of pae")
    path = SOURCE_ROOT.joinpath(*parts[1:])
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return ast.parse(path.read_text(), str(path))


def _class_node(target: str) -> ast.ClassDef:
    """The class definition of ``target`` (``pae.<module>.<Class>``) in its module's source."""
    module, name = target.rsplit(".", 1)
    for node in _module_tree(module).body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node
    raise ValueError(f"{target}: no class {name} in {module}")


def _constant(module: str, name: str, depth: int = 4) -> Any:
    """The literal value of the module-level constant ``name`` of ``module``, followed through
    ``from pae... import name`` (a default written as a named constant)."""
    for node in _module_tree(module).body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                return ast.literal_eval(node.value)
        imported = isinstance(node, ast.ImportFrom) and (node.module or "").startswith("pae")
        if imported and depth and any((a.asname or a.name) == name for a in node.names):
            return _constant(node.module, name, depth - 1)
    raise ValueError(f"{module}: no literal constant {name}")


def _annotation(node: ast.expr | None) -> Any:
    """The schema type of an annotation: a plain type, that type or None, else ``Any``."""
    if isinstance(node, ast.Name) and node.id in PLAIN_TYPES:
        return PLAIN_TYPES[node.id]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
        left, right = node.left, node.right
        if isinstance(right, ast.Constant) and right.value is None:
            inner = _annotation(left)
            return inner | None if inner is not Any else Any
    return Any


def _default(node: ast.expr | None, target: str, name: str) -> Any:
    """A literal default, or a named constant's (tuples as lists); no default: mandatory
    (``???``)."""
    if node is None:
        return MISSING
    try:
        if isinstance(node, ast.Name):
            value = _constant(target.rsplit(".", 1)[0], node.id)
        else:
            value = ast.literal_eval(node)
    except ValueError:
        raise ValueError(f"{target}: the default of {name} is not a literal") from None
    return list(value) if isinstance(value, tuple) else value


def _class_names(node: ast.ClassDef, attribute: str) -> tuple[str, ...]:
    """The strings of a class attribute holding a tuple of names (``from_run``)."""
    for statement in node.body:
        if isinstance(statement, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == attribute for t in statement.targets
        ):
            return tuple(ast.literal_eval(statement.value))
    return ()


def source_fields(
    target: str, leave_out: tuple[str, ...] = STEP_FILLED
) -> list[tuple[str, Any, Any]]:
    """The schema fields of ``target``: its constructor's keyword arguments (but ``self``,
    ``leave_out`` and its ``from_run``), or, for a dataclass without a constructor, its
    fields; each ``(name, type, dataclasses.field)``."""
    node = _class_node(target)
    skipped = {"self", *leave_out, *_class_names(node, "from_run")}
    pairs: list[tuple[str, ast.expr | None, ast.expr | None]] = []
    init = next(
        (s for s in node.body if isinstance(s, ast.FunctionDef) and s.name == "__init__"), None
    )
    if init is not None:
        args = init.args.args
        defaults = [None] * (len(args) - len(init.args.defaults)) + list(init.args.defaults)
        pairs += [(a.arg, a.annotation, d) for a, d in zip(args, defaults, strict=True)]
        pairs += [
            (a.arg, a.annotation, d)
            for a, d in zip(init.args.kwonlyargs, init.args.kw_defaults, strict=True)
        ]
    else:
        pairs += [
            (s.target.id, s.annotation, s.value)
            for s in node.body
            if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
        ]
    fields = []
    for name, annotation, default in pairs:
        if name in skipped:
            continue
        value = _default(default, target, name)
        kind = _annotation(annotation) if value is not MISSING else Any
        if isinstance(value, list | dict):
            spec = dataclasses.field(default_factory=lambda v=value: type(v)(v))
        else:
            spec = dataclasses.field(default=value)
        fields.append((name, kind if value is not None or kind is Any else kind | None, spec))
    return fields
