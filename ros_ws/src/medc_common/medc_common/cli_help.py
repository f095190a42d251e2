"""``--help`` for the node console scripts (medc-sim, medc-agent, medc-bridge) without starting a node.

A node's parameters are declared in its constructor, so listing them would take a running node (a
DDS participant on the current domain). Instead the help reads them from the source of the modules
that declare them: every ``p("name", default, "description", ...)`` call (the one-line form of
:func:`medc_common.params.declare` the nodes use) and every ``declare(node, "name", ...)``. Nothing is
imported from those modules, so ``--help`` works even before the ROS messages are built.
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import sys
from collections.abc import Sequence
from pathlib import Path

HELP_FLAGS = ("-h", "--help")


def wants_help(argv: Sequence[str] | None) -> bool:
    """Whether the command line (``sys.argv`` when None, program name first) asks for help."""
    args = list(sys.argv if argv is None else argv)[1:]
    return any(a in HELP_FLAGS for a in args)


class _Names:
    """Values of the names a module's parameter declarations use: its module-level constants and
    what it imports from modules that import without the ROS messages (medc_training, the contract).
    A name it cannot resolve stays as source text."""

    def __init__(self, tree: ast.Module) -> None:
        self.constants: dict[str, object] = {}
        self.imports: dict[str, tuple[str, str | None]] = {}
        for node in tree.body:
            target = node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1 else None
            if isinstance(target, ast.Name):
                with contextlib.suppress(ValueError):
                    self.constants[target.id] = ast.literal_eval(node.value)
        for node in ast.walk(tree):  # imports inside functions too (the nodes import lazily)
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for alias in node.names:
                    self.imports[alias.asname or alias.name] = (node.module, alias.name)
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    self.imports[alias.asname or alias.name] = (alias.name, None)

    def value(self, name: str) -> object:
        """The value of ``name``. Raises LookupError when it cannot be resolved."""
        import importlib

        if name in self.constants:
            return self.constants[name]
        if name not in self.imports:
            raise LookupError(name)
        module, attr = self.imports[name]
        try:
            if attr is None:
                return importlib.import_module(module)
            try:
                return importlib.import_module(f"{module}.{attr}")
            except ImportError:
                return getattr(importlib.import_module(module), attr)
        except Exception as exc:  # a module that needs the ROS messages, or anything else
            raise LookupError(name) from exc

    def evaluate(self, node: ast.AST) -> object:
        """The value of expression ``node`` (the project's own source) from literals and resolvable
        names. Raises LookupError when a name cannot be resolved."""
        try:
            return ast.literal_eval(node)
        except ValueError:
            pass
        if isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or):
            return self.evaluate(node.values[-1])  # `given or default`: the default
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        scope = {name: self.value(name) for name in names if name not in _BUILTINS}
        try:
            code = compile(ast.Expression(node), "<parameter>", "eval")
            return eval(code, {"__builtins__": _BUILTINS}, scope)
        except Exception as exc:
            raise LookupError(ast.unparse(node)) from exc

    def default(self, node: ast.AST) -> str:
        try:
            return repr(self.evaluate(node))
        except LookupError:
            return ast.unparse(node)

    def text(self, node: ast.AST) -> str:
        """A description: a string, or an f-string with its placeholders filled in where they resolve."""
        if isinstance(node, ast.JoinedStr):
            parts = []
            for value in node.values:
                if isinstance(value, ast.Constant):
                    parts.append(str(value.value))
                    continue
                expr = value.value  # type: ignore[attr-defined]
                try:
                    parts.append(str(self.evaluate(expr)))
                except LookupError:
                    parts.append("{" + ast.unparse(expr) + "}")
            return "".join(parts)
        try:
            return str(self.evaluate(node))
        except LookupError:
            return ast.unparse(node)


_BUILTINS = {"sorted": sorted, "len": len, "str": str, "list": list, "min": min, "max": max}


def module_source(module: str) -> Path:
    """The source file of ``module`` (found, not imported; its parent packages are imported).

    Raises:
        ModuleNotFoundError: no such module.
    """
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        raise ModuleNotFoundError(module)
    return Path(spec.origin)


def declared_parameters(*modules: str) -> list[tuple[str, str, str]]:
    """``(name, default as source, description)`` of every parameter the ``modules`` declare, in
    source order (the first declaration of a name wins)."""
    out: dict[str, tuple[str, str, str]] = {}
    for module in modules:
        tree = ast.parse(module_source(module).read_text())
        names = _Names(tree)
        calls = sorted((n for n in ast.walk(tree) if isinstance(n, ast.Call)),
                       key=lambda n: (n.lineno, n.col_offset))
        for call in calls:
            func = call.func
            name = func.id if isinstance(func, ast.Name) else None
            args = list(call.args)
            if name == "declare" and len(args) >= 4:
                args = args[1:]  # declare(node, name, default, description, ...)
            elif name != "p" or len(args) < 3:
                continue
            first = args[0]
            if not (isinstance(first, ast.Constant) and isinstance(first.value, str)):
                continue
            out.setdefault(first.value, (first.value, names.default(args[1]), names.text(args[2])))
    return list(out.values())


def node_help(program: str, summary: str, parameters: Sequence[tuple[str, str, str]], example: str) -> str:
    """The help text of a node console script."""
    lines = [f"usage: {program} [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] "
             "[-r __node:=NAME]]",
             "", summary.strip(), "", f"example: {example}", "",
             "ROS parameters (-p NAME:=VALUE; a YAML file with --params-file):"]
    for name, default, description in parameters:
        lines.append(f"  {name} (default {default})")
        lines.append(f"      {description}")
    lines += ["", "Topics and the whole contract: docs/ros-reference.md.",
              "-h, --help  show this help and exit (no node is started)"]
    return "\n".join(lines)


def print_node_help(program: str, summary: str, modules: Sequence[str], example: str) -> int:
    """Print :func:`node_help` for the parameters ``modules`` declare; returns exit status 0."""
    print(node_help(program, summary, declared_parameters(*modules), example))
    return 0
