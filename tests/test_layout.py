"""The package's import rule (ARCHITECTURE.md): every import points down, and there is no cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import psdfactory

PKG = Path(psdfactory.__file__).parent
CONTRACT = {"io", "config", "seeding", "manifest", "psd", "preflight"}
EDGES = {"cli", "report"}
# what each part may import from the package (besides itself)
MAY_IMPORT = {
    "contract": {"contract"},
    "scene": {"contract"},
    "learn": {"contract"},
    "deploy": {"learn", "contract"},
    "edge": {"scene", "learn", "deploy", "contract", "edge"},
}


def part(module: str) -> str:
    first = module.split(".")[1] if "." in module else ""
    if first in ("scene", "learn", "deploy"):
        return first
    return "edge" if first in EDGES else "contract"  # psdfactory itself (PsdError) is contract


def modules() -> dict[str, Path]:
    out = {}
    for f in PKG.rglob("*.py"):
        if f.name == "blender_job.py":  # runs inside Blender's Python, never imported
            continue
        rel = f.relative_to(PKG.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join(parts)] = f
    return out


def imports(module: str, path: Path, known: set[str]) -> set[str]:
    """The package modules that `module` imports, lazily imported ones included."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [f"{target}.{a.name}" for a in node.names]
            found |= {n for n in names if n in known} or ({target} if target in known else set())
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in known}
    found.discard(module)
    return found


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {m: imports(m, p, set(mods)) for m, p in mods.items()}


def test_the_graph_sees_the_imports():
    g = graph()
    assert "psdfactory.learn.runtime" in g["psdfactory.learn.cnn"]
    assert "psdfactory.scene.render.cycles" in g["psdfactory.scene.show"]  # a lazy import
    assert "psdfactory" in g["psdfactory.io"]  # PsdError


def test_every_import_points_down():
    wrong = [f"{m} → {t}" for m, targets in graph().items() for t in targets
             if part(t) != part(m) and part(t) not in MAY_IMPORT[part(m)]]
    assert not wrong, "imports against the rule in ARCHITECTURE.md:\n" + "\n".join(sorted(wrong))


def test_no_import_cycle():
    g = graph()
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for t in sorted(g[m]):
            if state.get(t) == 1:
                raise AssertionError("import cycle: " + " → ".join(path[path.index(t):] + [t]))
            if t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m, [m])
