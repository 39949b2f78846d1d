"""The project's modules import one another without cycles, and only downward through the
layers (docs/design.md, 1).

Every ``import`` and ``from ... import`` in the packages (fgslam, factors, devices) counts:
at module level, inside functions and under ``if TYPE_CHECKING``, relative ones resolved.
``from pkg import name`` is an import of the module ``pkg.name`` when there is one, else of
``pkg`` (its ``__init__``); importing ``a.b.c`` counts as an import of ``a.b.c`` only (Python
runs the packages' ``__init__`` first, which is no cycle). A cycle is a strongly connected
component of that graph; the failure names each import in it (module:line -> module)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fgslam", "factors", "devices")


def modules(root: Path, packages=PACKAGES) -> dict[str, tuple[Path, bool]]:
    """Module name -> (file, is a package's ``__init__``) of every module under ``root``."""
    out = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts.pop()
            out[".".join(parts)] = (f, is_pkg)
    return out


def import_graph(root: Path, packages=PACKAGES) -> dict[str, dict[str, int]]:
    """Module -> {imported project module: line of the first such import}."""
    mods = modules(root, packages)

    def known(name: str) -> str:
        while name not in mods and "." in name:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, dict[str, int]] = {}
    for name, (path, is_pkg) in mods.items():
        here = name if is_pkg else name.rpartition(".")[0]
        deps: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.split(".")[: len(here.split(".")) - node.level + 1]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                targets = [
                    f"{mod}.{a.name}" if f"{mod}.{a.name}" in mods else mod for a in node.names
                ]
            for t in targets:
                if t.split(".")[0] in packages:
                    deps.setdefault(known(t), node.lineno)
        deps.pop(name, None)
        graph[name] = deps
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in graph:
                    continue
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def describe(graph: dict[str, dict[str, int]], comp: list[str]) -> str:
    edges = [
        f"{v}:{line} -> {w}" for v in comp for w, line in sorted(graph[v].items()) if w in comp
    ]
    return "import cycle among " + ", ".join(comp) + ":\n  " + "\n  ".join(edges)


def test_no_import_cycles():
    graph = import_graph(ROOT)
    assert "fgslam.config" in graph and "factors.geometry" in graph  # the walk found the tree
    found = cycles(graph)
    assert not found, "\n".join(describe(graph, c) for c in found)


def test_a_planted_cycle_is_found(tmp_path):
    """The check itself: a function-level import closing a loop through a package's
    ``__init__`` and a relative import is reported, with its lines; the same tree without
    the closing import has none."""
    pkg = tmp_path / "fgslam"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from fgslam.sub.low import X\n")
    (pkg / "sub" / "low.py").write_text("X = 1\n\ndef f():\n    from .. import top\n")
    (pkg / "top.py").write_text("import fgslam.mid\n")
    (pkg / "mid.py").write_text("from fgslam import sub\n")
    graph = import_graph(tmp_path, ("fgslam",))
    found = cycles(graph)
    assert found == [["fgslam.mid", "fgslam.sub", "fgslam.sub.low", "fgslam.top"]]
    assert "fgslam.sub.low:4 -> fgslam.top" in describe(graph, found[0])
    (pkg / "sub" / "low.py").write_text("X = 1\n")
    assert cycles(import_graph(tmp_path, ("fgslam",))) == []


# The layers, bottom first (docs/design.md, 1). A module imports only modules of its own layer
# or of a layer below; within a layer, only its own folder or that folder's subfolders.
LAYERS = (
    ("factors", "devices"),  # measurement models and device drivers: no fgslam import
    ("fgslam.errors", "fgslam.choices"),  # the vocabulary: errors, the options' choices
    ("fgslam.config",),  # every parameter, read from TOML
    ("fgslam",),  # the rest of the package's root: events
    ("fgslam.scanmatch",),
    ("fgslam.frontend",),
    ("fgslam.io",),
    ("fgslam.sim",),
    ("fgslam.evaluation",),
    ("fgslam.slam",),
    ("fgslam.session",),  # map reuse: saved sessions, localization on them
    ("fgslam.online",),
    ("fgslam.sweep",),  # many runs on Dask
    ("fgslam.cli", "fgslam.__main__"),
)


def layer_of(module: str, layers=LAYERS) -> int:
    """Index of the layer holding ``module``: the longest prefix named in ``layers``."""
    best, found = -1, -1
    for i, names in enumerate(layers):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > best:
                best, found = len(name), i
    if found < 0:
        raise KeyError(f"{module} is in no layer")
    return found


def folder_of(module: str, graph) -> str:
    """A package's own name, else its parent package."""
    is_pkg = any(m.startswith(module + ".") for m in graph)
    return module if is_pkg else module.rpartition(".")[0]


def upward_imports(graph, layers=LAYERS) -> list[str]:
    """Every import of a higher layer, or within a layer of a module outside the importer's
    folder and its subfolders (a parent folder's module or a sibling folder's)."""
    bad = []
    for v, deps in sorted(graph.items()):
        lv, fv = layer_of(v, layers), folder_of(v, graph)
        for w, line in sorted(deps.items()):
            lw = layer_of(w, layers)
            inside = w == fv or w.startswith(fv + ".")
            if lw > lv:
                bad.append(f"{v}:{line} -> {w} (layer {lw} above {lv})")
            elif lw == lv and not inside:
                bad.append(f"{v}:{line} -> {w} (outside {fv}/)")
    return bad


def test_imports_only_downward():
    graph = import_graph(ROOT)
    assert {layer_of(m) for m in graph} == set(range(len(LAYERS)))  # every layer is populated
    bad = upward_imports(graph)
    assert not bad, "upward imports:\n  " + "\n  ".join(bad)


def test_a_planted_upward_import_is_found(tmp_path):
    """The check itself: a layer importing a higher one, and a subfolder importing its parent
    folder's module, are reported; the same tree without them has none."""
    pkg = tmp_path / "fgslam"
    for d in ("io/readers", "slam"):
        (pkg / d).mkdir(parents=True)
    for d in ("", "io", "io/readers", "slam"):
        (pkg / d / "__init__.py").write_text("")
    (pkg / "config.py").write_text("")
    (pkg / "io" / "logfile.py").write_text("from fgslam.io.readers import common\n")
    (pkg / "io" / "readers" / "common.py").write_text("from fgslam import config\n")
    (pkg / "slam" / "step.py").write_text("from fgslam.io import logfile\n")
    layers = (("fgslam",), ("fgslam.io",), ("fgslam.slam",))
    assert upward_imports(import_graph(tmp_path, ("fgslam",)), layers) == []
    (pkg / "io" / "readers" / "common.py").write_text("from fgslam.io import logfile\n")
    (pkg / "config.py").write_text("def f():\n    from fgslam.slam import step\n")
    bad = upward_imports(import_graph(tmp_path, ("fgslam",)), layers)
    assert bad == [
        "fgslam.config:2 -> fgslam.slam.step (layer 2 above 0)",
        "fgslam.io.readers.common:1 -> fgslam.io.logfile (outside fgslam.io.readers/)",
    ]
