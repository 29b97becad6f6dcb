"""Every message of every connection is defined in `protocol/`, nowhere else: no module outside
it defines a message model or names a union of messages of its own."""

from __future__ import annotations

import ast
from pathlib import Path

from protocol import MESSAGE_TYPES
from tests.test_imports import ROOT, modules

MESSAGES = {cls.__name__ for cls in MESSAGE_TYPES.values()} | {"Message"}


def _name(node: ast.expr) -> str:
    """`Forces`, `p.Forces`, `protocol.Forces` -> `Forces`; anything else -> ''."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
        return node.attr
    return ""


def _union(node: ast.expr) -> list[str] | None:
    """The names a `A | B | C` expression joins, or None for anything else."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
        left, right = _union(node.left), _union(node.right)
        return None if left is None or right is None else left + right
    name = _name(node)
    return [name] if name else None


def definitions(path: Path) -> list[str]:
    """Message models and unions of messages that `path` defines, as `line: what`."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ClassDef) and any(_name(b) in MESSAGES for b in node.bases):
            out.append((node.lineno, f"class {node.name}"))
        elif isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
            joined = _union(node.value)
            if joined and len(joined) > 1 and set(joined) <= MESSAGES:
                out.append((node.lineno, " | ".join(joined)))
    return [f"{line}: {what}" for line, what in sorted(out)]


def test_no_message_is_defined_outside_the_protocol() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{what}"
        for module, path in modules(ROOT).items()
        if not module.startswith("protocol")
        for what in definitions(path)
    ]
    assert not found, "use the protocol's definitions: " + "; ".join(found)


def test_a_union_of_messages_is_found(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text(
        "import protocol as p\n"
        "from protocol import Control, Forces, SimParams\n"
        "Steering = SimParams | Control | Forces\n"
        "Mixed: object = p.Frame | int\n"
        "class Mine(p.Message):\n"
        "    pass\n"
    )
    assert definitions(source) == ["3: SimParams | Control | Forces", "5: class Mine"]
