"""The package's shape: every module imports, no import circles, no private names across modules, the
onboarding stages declared once (pipeline/onboard/stages/__init__.py), and the query wing's ranking steps
listed once (pipeline/query/steps/__init__.py), none of them importing the API."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "pipeline"
STAGE_DECLARATION = PACKAGE / "onboard" / "stages" / "__init__.py"
STEP_DECLARATION = PACKAGE / "query" / "steps" / "__init__.py"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def runtime_imports(tree: ast.AST, typing_too: bool = False):
    """Import nodes anywhere in the module (function-level ones too), except ``if TYPE_CHECKING:``
    blocks, which never run (``typing_too``: those as well)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and is_type_checking(node) and not typing_too:
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def resolve_from(mod: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.split(".")
    if not MODULES[mod].name == "__init__.py":
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def graph(typing_too: bool = False) -> tuple[dict[str, set[str]], list[str]]:
    """Module -> the package's modules it imports (``typing_too``: type-checking imports as well); and
    every private name imported across modules."""
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    private: list[str] = []
    for mod, path in MODULES.items():
        for node in runtime_imports(ast.parse(path.read_text(), str(path)), typing_too):
            if isinstance(node, ast.Import):
                edges[mod] |= {a.name for a in node.names if a.name in MODULES}
                continue
            source = resolve_from(mod, node)
            for a in node.names:
                sub = f"{source}.{a.name}"
                if sub in MODULES:
                    edges[mod].add(sub)
                elif source in MODULES:
                    edges[mod].add(source)
                    if a.name.startswith("_") and not a.name.endswith("__") and source != mod:
                        private.append(f"{mod}: from {source} import {a.name}")
        edges[mod].discard(mod)
    return edges, private


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("mod", [m for m in MODULES if not m.endswith("__main__")])
def test_every_module_imports(mod):
    importlib.import_module(mod)


def test_no_import_cycles():
    edges, _ = graph()
    assert edges["pipeline.onboard.engines.ray"] >= {
        "pipeline.onboard.engines.base"
    }  # the graph sees imports
    assert cycles(edges) == []


def test_no_import_cycles_even_for_type_checking():
    """Type-only imports close no circle either (the stages read their config through a protocol)."""
    edges, _ = graph(typing_too=True)
    assert "pipeline.onboard.config" in edges["pipeline.onboard.engines.base"]
    assert cycles(edges) == []


def reachable_from_entry_points(edges: dict[str, set[str]]) -> set[str]:
    """Modules the ``oscar`` command and ``python -m pipeline...`` can load: imports, modules named in
    strings (the verb table, the model adapter registry), each package's ``__main__`` and parents."""
    for mod, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in MODULES:
                edges[mod].add(node.value)
    seen: set[str] = set()
    stack = ["pipeline", "pipeline.cli", "pipeline.__main__"]
    while stack:
        mod = stack.pop()
        if mod in seen:
            continue
        seen.add(mod)
        stack.extend(edges[mod])
        if f"{mod}.__main__" in MODULES:
            stack.append(f"{mod}.__main__")
        parts = mod.split(".")
        stack.extend(".".join(parts[:i]) for i in range(1, len(parts)))
    return seen


def test_package_ships_no_test_only_code():
    """Every module of the package is reachable from its commands: code only tests use lives in tests/."""
    edges, _ = graph()
    assert set(MODULES) - reachable_from_entry_points(edges) == set()
    assert not [m for m in MODULES if "fixture" in m or m.split(".")[-1].startswith("test")]


def test_reachability_sees_an_orphan():
    edges = graph()[0]
    edges["pipeline.sql.fixtures"] = {"pipeline.store"}  # imports the package; nothing imports it
    reached = reachable_from_entry_points(edges)
    assert "pipeline.sql.fixtures" not in reached and "pipeline.sql.cli" in reached


def test_cycle_finder_finds_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_private_names_across_modules():
    _, private = graph()
    assert private == []


def test_engines_are_siblings():
    from pipeline.onboard.engines.base import Engine
    from pipeline.onboard.engines.local import LocalEngine
    from pipeline.onboard.engines.ray import RayEngine

    assert LocalEngine.__bases__ == (Engine,) and RayEngine.__bases__ == (Engine,)
    edges, _ = graph()
    assert "pipeline.onboard.engines.local" not in edges["pipeline.onboard.engines.ray"]
    assert "pipeline.onboard.engines.ray" not in edges["pipeline.onboard.engines.local"]


def test_mesh_code_does_not_know_onboarding():
    edges, _ = graph()
    for mod, deps in edges.items():
        if mod.startswith("pipeline.mesh"):
            assert not [d for d in deps if d.startswith("pipeline.onboard")], mod


def stage_literals(path: Path, names: set[str]) -> list[str]:
    """Stage names written out in ``path``: a sequence literal naming two or more stages, or the name
    of a stage that only the declaration may mention (the embedding stages)."""
    found = []
    only_declared = {n for n in names if n.startswith("embed")}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Tuple | ast.List | ast.Set):
            named = {e.value for e in node.elts if isinstance(e, ast.Constant) and e.value in names}
            if len(named) >= 2:
                found.append(f"{path.name}:{node.lineno}: {sorted(named)}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value in only_declared or node.value.split(":")[0] in only_declared:
                found.append(f"{path.name}:{node.lineno}: {node.value!r}")
    return found


def test_stages_declared_once():
    from pipeline.onboard.stages import STAGE_NAMES, STAGES

    assert STAGE_NAMES == ("render", "caption", "embed_text", "embed_image", "probe", "patches", "features")
    assert [s.input for s in STAGES] == [None, "render", "caption", "render", "render", "render", "render"]
    assert stage_literals(STAGE_DECLARATION, set(STAGE_NAMES))  # the check sees the declaration
    # the onboarding wing iterates the declaration (readers look fingerprints up by key in a run's record)
    elsewhere = [
        hit
        for mod, path in MODULES.items()
        if mod.startswith("pipeline.onboard") and path != STAGE_DECLARATION
        for hit in stage_literals(path, set(STAGE_NAMES))
    ]
    assert elsewhere == []


def test_steps_follow_the_declaration():
    from pipeline.onboard.cli import build_parser
    from pipeline.onboard.config import OnboardConfig
    from pipeline.onboard.stages import STAGE_NAMES

    paper = OnboardConfig(profile="paper").resolve()
    assert [s.key for s in paper.steps] == [
        "render",
        "caption",
        "embed_text",
        "embed_image:view_encoder",
        "embed_image:clip_image_encoder",
        "features",
    ]
    assert [s.input for s in paper.steps] == [None, "render", "caption", "render", "render", "render"]
    assert paper.step("features").dataset == "view_features"
    assert paper.fingerprints == OnboardConfig(profile="paper").fingerprints()
    offline = OnboardConfig().resolve()
    assert offline.step("patches").dataset == "view_patches" and offline.step("patches").role == "learned_encoder"
    args = build_parser().parse_args(["lib", "--store", "s", "--no-patch-tokens"])
    assert args.no_patch_tokens and not build_parser().parse_args(["lib", "--store", "s"]).no_patch_tokens
    assert "patches" not in [s.key for s in OnboardConfig(patch_tokens=False).resolve().steps]
    force = next(a for a in build_parser()._actions if a.dest == "force")
    assert tuple(force.choices) == STAGE_NAMES
    with pytest.raises(ValueError, match="unknown --force stage"):
        OnboardConfig(force=("nope",))


def test_disabled_stage_has_no_step():
    """``--local-features none``: the features stage's enabled hook drops its step from the run (and
    ``--probes 0`` the probe stage's; a profile without a learned encoder has no probe step)."""
    from pipeline.adapter.probes import ProbeConfig
    from pipeline.localfeat.config import FeatureConfig
    from pipeline.onboard.config import OnboardConfig

    run = OnboardConfig(features=FeatureConfig(detector="none")).resolve()
    assert "features" not in [s.key for s in run.steps]
    assert "features" not in run.fingerprints
    no_probes = OnboardConfig(probes=ProbeConfig(per_mesh=0)).resolve()  # --probes 0
    assert "probe" not in no_probes.fingerprints and "probe" in OnboardConfig().resolve().fingerprints
    assert "probe" not in OnboardConfig(profile="paper").resolve().fingerprints  # no learned encoder
    orb = OnboardConfig(features=FeatureConfig(detector="orb")).resolve()
    assert orb.step("features").fingerprint != OnboardConfig().resolve().step("features").fingerprint


def test_profile_and_fingerprints_resolved_once_per_run(tmp_path, offline_models, monkeypatch):
    """One run resolves its config once (one profile, one set of fingerprints), then passes it down."""
    import shutil

    from conftest import SAMPLE_LIBRARY
    from onboard_helpers import onboard

    import pipeline.onboard.config as config
    from pipeline.mesh.settings import RenderConfig

    calls = {"get_profile": 0, "fingerprint": 0}
    real_profile, real_render_fp = config.get_profile, RenderConfig.fingerprint

    def counting_profile(*a, **kw):
        calls["get_profile"] += 1
        return real_profile(*a, **kw)

    def counting_render_fp(self):
        calls["fingerprint"] += 1
        return real_render_fp(self)

    monkeypatch.setattr(config, "get_profile", counting_profile)
    monkeypatch.setattr(RenderConfig, "fingerprint", counting_render_fp)
    lib = tmp_path / "lib"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    summary = onboard(lib, tmp_path / "store", offline_models, render=RenderConfig(resolution=64))
    assert summary.rendered == 1 and summary.captioned == 1
    assert calls == {"get_profile": 1, "fingerprint": 1}


# ---------------------------------------------------------------- the query wing: ranking as a list of steps
def step_modules() -> set[str]:
    """The ranking step modules: every module of pipeline/query/steps/ but the declaration and the state."""
    folder = STEP_DECLARATION.parent
    return {module_name(p) for p in folder.glob("*.py") if p.name not in ("__init__.py", "state.py")}


def reachable(edges: dict[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for dep in edges[todo.pop()] - seen:
            seen.add(dep)
            todo.append(dep)
    return seen


def sequence_literals(path: Path, names: set[str]) -> list[str]:
    """Tuple, list or set literals in ``path`` that name two or more of ``names``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Tuple | ast.List | ast.Set):
            named = {e.value for e in node.elts if isinstance(e, ast.Constant) and e.value in names}
            if len(named) >= 2:
                found.append(f"{path.name}:{node.lineno}: {sorted(named)}")
    return found


def test_ranking_steps_do_not_import_the_api():
    edges, _ = graph()
    assert "pipeline.query.steps" in edges["pipeline.query.api"]  # the graph sees the step package
    steps = [m for m in MODULES if m.startswith("pipeline.query.steps")]
    assert len(steps) > 5
    for mod in steps:
        assert "pipeline.query.api" not in reachable(edges, mod), mod


def test_step_lists_are_the_only_place_steps_are_listed():
    from pipeline.query.modes import MODES
    from pipeline.query.steps import STEP_LISTS

    assert tuple(STEP_LISTS) == MODES  # the modes are the step lists
    modules = step_modules()
    listed = {step.run.__module__ for steps in STEP_LISTS.values() for step in steps}
    assert listed == modules  # every step module is in a list, and every list entry is a step module
    for steps in STEP_LISTS.values():
        for step in steps:
            assert step.run is importlib.import_module(step.run.__module__).run  # each module's one entry
    edges, _ = graph()
    importers = {mod for mod, deps in edges.items() if deps & modules}
    assert importers == {"pipeline.query.steps"}  # nothing else (nor another step) imports a step
    # the modes are written out once (pipeline/query/modes.py, for --help), and as the declaration's keys
    allowed = {STEP_DECLARATION, PACKAGE / "query" / "modes.py"}
    assert sequence_literals(PACKAGE / "query" / "modes.py", set(MODES))  # the check sees them
    elsewhere = [
        hit for path in MODULES.values() if path not in allowed for hit in sequence_literals(path, set(MODES))
    ]
    assert elsewhere == []


def test_the_api_holds_no_ranking_logic():
    """api.py opens the store and the models and hands them to the steps: no array maths, no mode branches."""
    path = PACKAGE / "query" / "api.py"
    tree = ast.parse(path.read_text())
    imported = {
        a.name.split(".")[0] for n in runtime_imports(tree) if isinstance(n, ast.Import) for a in n.names
    }
    imported |= {
        (n.module or "").split(".")[0] for n in runtime_imports(tree) if isinstance(n, ast.ImportFrom)
    }
    assert not imported & {"numpy", "torch"}
    modes = [
        n.lineno
        for n in ast.walk(tree)
        if isinstance(n, ast.Compare)
        and any(isinstance(c, ast.Constant) and c.value in ("text-only", "image-only") for c in n.comparators)
    ]
    assert modes == []
