"""The package's layers: no import circle, and no import from a lower layer up to a higher one.

The order (docs/code_layout.md), lowest first; a module may import from its own layer and
the layers below it:

    base        geometry, cpu_backend, progress
    data        data/, config
    paper       detection/, depth/, models/
    services    evaluation/ (scoring), drawing/ (pictures), training/ (run plumbing)
    tracking    tracking/ (objects over time: the multi-object trackers, numpy/scipy)
    weights     weights/ (PyTorch import, pretrained backbones)
    builders    builders/ (config -> model, anchors, priors, transforms, evaluators)
    runs        trainers/, trained/ (a trained model from a run folder or converted weights)
    deploy      deploy/ (ONNX export, ONNX Runtime / OpenVINO)
    guard       guard/ (the accuracy guard: its statistics, rules and verdicts on exports)
    api         api/ (the inference API: Detector3D, DepthPredictor)
    streams     streams/ (video files, cameras, image sequences through a detector)
    cli         cli/ (evaluate, predict)

Imports are read with ``ast`` from every ``.py`` file: module level, inside functions and
under ``TYPE_CHECKING`` alike (each is an arrow a reader has to follow).
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYERS = (
    ("base", ("gac_jax.geometry", "gac_jax.cpu_backend", "gac_jax.progress")),
    ("data", ("gac_jax.data", "gac_jax.config")),
    ("paper", ("gac_jax.detection", "gac_jax.depth", "gac_jax.models")),
    ("services", ("gac_jax.evaluation", "gac_jax.drawing", "gac_jax.training")),
    ("tracking", ("gac_jax.tracking",)),
    ("weights", ("gac_jax.weights",)),
    ("builders", ("gac_jax.builders",)),
    ("runs", ("gac_jax.trainers", "gac_jax.trained")),
    ("deploy", ("gac_jax.deploy",)),
    ("guard", ("gac_jax.guard",)),
    ("api", ("gac_jax.api",)),
    ("streams", ("gac_jax.streams",)),
    ("cli", ("gac_jax.cli",)),
)


def module_files(root: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of ``root/package``."""
    out = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def import_graph(root: Path, package: str = "gac_jax") -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports (``from P import m`` counts as ``P.m``
    when ``m`` is a module, else as ``P``)."""
    modules = module_files(root, package)

    def resolve(name: str) -> str | None:
        parts = name.split(".")
        while parts:
            if ".".join(parts) in modules:
                return ".".join(parts)
            parts.pop()
        return None

    graph = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        here = name.split(".") if is_package else name.split(".")[:-1]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {resolve(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = here[: len(here) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                for a in node.names:
                    targets.add(resolve(f"{base}.{a.name}") or resolve(base))
        graph[name] = {t for t in targets if t and t != name}
    return graph


def script_graph(folder: Path) -> dict[str, set[str]]:
    """Scripts of one folder (``benchmarks/``) importing each other by file name."""
    names = {p.stem: p for p in folder.glob("*.py")}
    graph = {}
    for name, path in names.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level:
                targets.add(node.module or "")
        graph[name] = {t for t in targets if t in names and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def layer_of(module: str, layers=LAYERS) -> int | None:
    for rank, (_, prefixes) in enumerate(layers):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return None


def upward_imports(graph: dict[str, set[str]], layers=LAYERS) -> list[str]:
    """``a -> b`` for every import from a lower layer to a higher one."""
    bad = []
    for a, targets in sorted(graph.items()):
        for b in sorted(targets):
            la, lb = layer_of(a, layers), layer_of(b, layers)
            if la is not None and lb is not None and lb > la:
                bad.append(f"{a} ({layers[la][0]}) -> {b} ({layers[lb][0]})")
    return bad


def test_the_library_has_no_import_circle():
    assert cycles(import_graph(REPO)) == []


def test_the_benchmarks_have_no_import_circle():
    assert cycles(script_graph(REPO / "benchmarks")) == []


def test_every_module_has_a_layer():
    unplaced = [m for m in import_graph(REPO) if m != "gac_jax" and layer_of(m) is None]
    assert unplaced == [], f"add these to LAYERS (and docs/code_layout.md): {unplaced}"


def test_no_import_runs_from_a_lower_layer_to_a_higher_one():
    assert upward_imports(import_graph(REPO)) == []


def test_the_package_root_holds_only_the_base_modules_and_config():
    root = sorted(p.name for p in (REPO / "gac_jax").glob("*.py"))
    assert root == ["__init__.py", "config.py", "cpu_backend.py", "geometry.py", "progress.py"]


def test_the_checks_catch_a_circle_and_an_upward_import(tmp_path):
    """The checkers on a small made-up package: a -> b -> a, and low importing high lazily."""
    pkg = tmp_path / "gac_jax"
    (pkg / "low").mkdir(parents=True)
    (pkg / "high").mkdir()
    for f in ("__init__.py", "low/__init__.py", "high/__init__.py"):
        (pkg / f).write_text("")
    (pkg / "low" / "a.py").write_text("from gac_jax.low import b\n")
    (pkg / "low" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n"
    )
    (pkg / "low" / "c.py").write_text("def f():\n    from gac_jax.high.d import g\n")
    (pkg / "high" / "d.py").write_text("from ..low.c import f\ndef g(): ...\n")
    graph = import_graph(tmp_path)
    assert graph["gac_jax.low.b"] == {"gac_jax.low.a"}  # relative import under TYPE_CHECKING
    layers = (("low", ("gac_jax.low",)), ("high", ("gac_jax.high",)))
    assert cycles(graph) == [
        ["gac_jax.high.d", "gac_jax.low.c"],
        ["gac_jax.low.a", "gac_jax.low.b"],
    ]
    assert upward_imports(graph, layers) == ["gac_jax.low.c (low) -> gac_jax.high.d (high)"]
