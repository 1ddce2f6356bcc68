"""The architecture, checked: layers import one way, no import circles, no private
names across modules, no imports hidden in functions outside the command line, and
``import jaxlift`` changes no global state (matplotlib's backend, jax's float64 flag)."""

import ast
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PKG = ROOT / "jaxlift"
# lowest first: a module may import from its own layer and the layers before it
LAYERS = (
    "model", "analysis", "calibrate", "posterior", "control", "report", "workflows", "fleet",
    "cli",
)  # fmt: skip


def _modname(path: pathlib.Path) -> str:
    name = "jaxlift." + ".".join(path.relative_to(PKG).with_suffix("").parts)
    return name.removesuffix(".__init__")


def _modules() -> dict[str, pathlib.Path]:
    return {_modname(p): p for p in sorted(PKG.rglob("*.py"))}


def _imports(name: str, path: pathlib.Path, top_level_only: bool = True):
    """(target module, imported names, node) of every `from jaxlift... import` in a file."""
    tree = ast.parse(path.read_text())
    pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target == "jaxlift" or target.startswith("jaxlift."):
                yield target, [a.name for a in node.names], node


def _layer(name: str) -> int:
    parts = name.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else len(LAYERS)


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        deps = set()
        for target, names, _ in _imports(name, path):
            if target in mods:
                deps.add(target)
            deps |= {f"{target}.{n}" for n in names if f"{target}.{n}" in mods}
        graph[name] = deps
    return graph


def test_every_module_is_in_a_layer():
    top = ("jaxlift", "jaxlift.__main__")
    outside = [m for m in _modules() if _layer(m) == len(LAYERS) and m not in top]
    assert outside == [], f"modules outside the layers {LAYERS}: {outside}"


def test_layers_import_one_way():
    upward = [
        f"{m} -> {d}"
        for m, deps in _graph().items()
        for d in deps
        if m != "jaxlift" and _layer(d) > _layer(m)
    ]
    assert upward == [], "imports from a higher layer:\n" + "\n".join(upward)


def test_computation_never_imports_plotting():
    computing = ("model", "analysis", "calibrate", "posterior", "control")
    bad = []
    for name, path in _modules().items():
        if name.split(".")[1:2] and name.split(".")[1] in computing:
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    targets = [("." * node.level) + (node.module or "")]
                else:
                    continue
                if any(t.startswith(("matplotlib", "..report", "jaxlift.report")) for t in targets):
                    bad.append(f"{name}: {ast.unparse(node)}")
    assert bad == [], f"computation modules that plot or write reports: {bad}"


def test_no_import_circles():
    graph = _graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        for d in graph.get(m, ()):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d) :] + [d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [m])
    assert cycles == [], f"import circles: {cycles}"


def test_no_private_names_across_modules():
    bad = [
        f"{name}: from {target} import {n}"
        for name, path in _modules().items()
        for target, names, _ in _imports(name, path, top_level_only=False)
        for n in names
        if n.startswith("_") and not n.startswith("__")
    ]
    assert bad == [], "private names imported across modules:\n" + "\n".join(bad)


def test_imports_inside_functions_only_in_the_command_line():
    """The command line imports jaxlift inside its functions, after switching jax to
    float64 at the program's start (modules create jax arrays when imported, which
    must then already be float64), and so that a bad argument is answered before the
    seconds-long import of jax, diffrax and ArviZ. Nothing else imports inside a
    function."""
    bad = []
    for name, path in _modules().items():
        if name.startswith("jaxlift.cli"):
            continue
        tree = ast.parse(path.read_text())
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom) and id(node) not in top:
                bad.append(f"{name}:{node.lineno}: {ast.unparse(node)}")
    assert bad == [], "imports inside functions:\n" + "\n".join(bad)


@pytest.mark.parametrize("backend", ["svg", "pdf"])
def test_import_leaves_global_state_alone(backend):
    code = (
        "import matplotlib, jax, pkgutil, importlib\n"
        "import jaxlift\n"
        "for m in pkgutil.walk_packages(jaxlift.__path__, 'jaxlift.'):\n"
        "    if not m.name.endswith('__main__'):\n"
        "        importlib.import_module(m.name)\n"
        "print(matplotlib.get_backend(), jax.config.read('jax_enable_x64'))\n"
    )
    env = {**os.environ, "MPLBACKEND": backend}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [backend, "False"]


def test_version_from_metadata():
    from importlib.metadata import version

    import jaxlift

    assert jaxlift.__version__ == version("jaxlift")
    out = subprocess.run(
        [sys.executable, "-m", "jaxlift", "--version"], capture_output=True, text=True, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"jaxlift {version('jaxlift')}"


def test_no_file_points_outside_the_repository():
    """The specification is the project's own docs/; nothing cites the steering folder."""
    tracked = subprocess.run(
        ["git", "ls-files"], capture_output=True, text=True, cwd=ROOT, check=True
    ).stdout.split()
    bad = []
    for rel in tracked:
        if rel == "tests/test_architecture.py":  # names the needles
            continue
        p = ROOT / rel
        if p.suffix in {".py", ".md", ".toml", ".yml", ".yaml", ".txt", ".json"} and p.exists():
            text = p.read_text(errors="replace")
            for needle in ("../" + "shared", "STACK-NOTES", "reference/thesis.md"):
                if needle in text:
                    bad.append(f"{rel}: {needle}")
            for spec in ("MODEL.md", "DATA.md", "CONTROL.md"):
                if spec in text:
                    bad.append(f"{rel}: {spec}")
    assert bad == [], "files citing documents outside the repository:\n" + "\n".join(bad)
