"""The layout rules of the repository, checked on the source tree (docs/layout.md).

- imports run along the data flow: every module belongs to one stage and imports only from its own stage or the
  ones it builds on (:data:`STAGES`): the core, then two wings — training (data → labels → synth → model → render →
  train → eval) and shipping (runtime → predict, serve; the runtime is the one predictor path) —, export the bridge
  between them, then quickstart → commands → cli; no two modules import each other, directly or through others;
- no function is longer than 60 lines, except a numba kernel or one whose docstring gives the reason
  (a line starting with ``Long:``);
- the packages pyproject.toml installs are the package folders of the tree;
- README.md's tour names every package and top-level module, and every path it names exists;
- the documentation is self-contained (no pointer to notes outside the repository);
- each contract has one definition: the ONNX tensor names and the HTTP error body are spelled out once;
- files are written atomically one way (`occflownet.files.atomic_path`);
- one predictor path: only ``occflownet/runtime.py`` builds model feeds and runs an onnxruntime session, and only
  the contract rescales intrinsics.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = {"occflownet": REPO / "occflownet", "occflownet.export": REPO / "export",
                "occflownet.serve": REPO / "serve"}
MAX_LINES = 60

# Stages: (name, module prefixes, the stages it builds on). A module's stage is that of its longest matching prefix;
# it may import from its own stage and from every stage it builds on, directly or through them.
STAGES = (
    ("core", ("occflownet", "occflownet.occ3d", "occflownet.geometry", "occflownet.rig", "occflownet.contract",
              "occflownet.pictures", "occflownet.voxel_walk", "occflownet.voxel_walk_numba", "occflownet.files",
              "occflownet.choices", "occflownet.options", "occflownet.worker_processes", "occflownet.heap",
              "occflownet.viewer"), ()),
    # the training wing
    ("data", ("occflownet.data",), ("core",)),
    ("labels", ("occflownet.labels",), ("data",)),
    ("synth", ("occflownet.synth",), ("labels",)),
    ("model", ("occflownet.model",), ("synth",)),
    ("render", ("occflownet.render",), ("model",)),
    ("train", ("occflownet.train",), ("render",)),
    # the shipping wing (torch-free: the runtime's torch predictor is handed a model, it imports no model code)
    ("runtime", ("occflownet.runtime",), ("core",)),
    ("predict", ("occflownet.predict",), ("runtime",)),
    ("serve", ("occflownet.serve",), ("runtime",)),
    # evaluation runs the training wing's data through the one predictor path; export bridges the wings
    ("eval", ("occflownet.eval",), ("train", "runtime")),
    ("export", ("occflownet.export",), ("eval", "predict")),
    ("quickstart", ("occflownet.quickstart",), ("export", "serve")),
    ("commands", ("occflownet.commands",), ("quickstart",)),
    ("cli", ("occflownet.cli", "occflownet.__main__"), ("commands",)),
)


def _builds_on() -> dict[str, set[str]]:
    """{stage: the stages it may import from (itself and everything it builds on, transitively)}."""
    direct = {name: set(bases) for name, _, bases in STAGES}
    out = {}
    for name, _, _ in STAGES:                                   # STAGES lists every stage after its bases
        out[name] = {name}.union(*(out[b] for b in direct[name]))
    return out


BUILDS_ON = _builds_on()


def _modules() -> dict[str, Path]:
    """{dotted module name: file} of every module the package installs."""
    out = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("")
            parts = [] if rel.parts == ("__init__",) else list(rel.parts)
            if parts and parts[-1] == "__init__":
                parts = parts[:-1]
            if package == "occflownet" and parts and f"occflownet.{parts[0]}" in PACKAGE_DIRS:
                continue                                        # a mapped package, listed under its own folder
            out[".".join([package, *parts])] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """The package modules ``name`` imports (at module level or inside functions)."""
    is_package = path.name == "__init__.py"
    base = name.split(".") if is_package else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                module = ".".join(base[:len(base) - node.level + 1] + ([module] if module else []))
            candidates = [module] + [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        for c in candidates:
            while c and c not in MODULES:                        # `import occflownet.data.index` → that module
                c = c.rpartition(".")[0]
            if c and c != name:
                found.add(c)
    return found


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _stage(name: str) -> str:
    best, stage = -1, None
    for candidate, prefixes, _ in STAGES:
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > best:
                best, stage = len(p), candidate
    if stage is None:
        raise AssertionError(f"{name} belongs to no stage: add it to STAGES in tests/test_layout.py")
    return stage


def test_every_module_has_a_stage():
    for name in MODULES:
        _stage(name)


def test_stages_build_only_on_earlier_stages():
    order = [name for name, _, _ in STAGES]
    assert all(order.index(b) < order.index(name) for name, _, bases in STAGES for b in bases)


def test_imports_run_along_the_data_flow():
    wrong = [f"{a} ({_stage(a)}) imports {b} ({_stage(b)})"
             for a, targets in GRAPH.items() for b in targets
             if _stage(b) not in BUILDS_ON[_stage(a)] and b != "occflownet"]
    assert not wrong, "imports against the data flow:\n  " + "\n  ".join(sorted(wrong))


def test_no_import_cycles():
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(GRAPH[node]):
            if nxt == "occflownet":                              # the package __init__ imports nothing
                continue
            if state.get(nxt) == "open":
                cycles.append(" → ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for name in sorted(GRAPH):
        if name not in state:
            visit(name, [name])
    assert not cycles, "import cycles:\n  " + "\n  ".join(cycles)


def _python_files():
    roots = [*PACKAGE_DIRS.values(), REPO / "benchmarks", REPO / "tests", REPO / "docker", REPO / "embed"]
    return [p for root in roots for p in sorted(root.rglob("*.py")) if "build" not in p.parts]


def _is_numba_kernel(fn: ast.FunctionDef) -> bool:
    names = {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in fn.decorator_list}
    return bool(names & {"njit", "numba.njit", "jit", "numba.jit"})


def test_no_long_functions():
    long = []
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                doc = ast.get_docstring(node) or ""
                reason = any(line.strip().startswith("Long:") for line in doc.splitlines())
                if lines > MAX_LINES and not _is_numba_kernel(node) and not reason:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, f"functions over {MAX_LINES} lines without a 'Long:' reason:\n  " + "\n  ".join(long)


def test_pyproject_installs_every_package_folder():
    tomllib = pytest.importorskip("tomllib")                     # Python >= 3.11
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(config["packages"])
    on_disk = {name for name, path in MODULES.items() if path.name == "__init__.py"}
    assert listed == on_disk
    assert config["package-dir"] == {k: v.name for k, v in PACKAGE_DIRS.items() if k != "occflownet"}


def _tour() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## Tour", 1)[1].split("\n## ", 1)[0]
    return [p for row in section.splitlines() if row.startswith("| `")
            for p in re.findall(r"`([^`]+)`", row.split("|")[1])]


def test_readme_tour_matches_the_tree():
    tour = _tour()
    missing = [p for p in tour if not (REPO / p.rstrip("/")).exists()]
    assert not missing, f"README tour names paths that do not exist: {missing}"
    wanted = [f"{p.relative_to(REPO)}/" if p.is_dir() else str(p.relative_to(REPO))
              for p in (REPO / "occflownet").iterdir()
              if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")]
    wanted += ["export/", "serve/", "docker/", "embed/", "benchmarks/"]
    unnamed = [w for w in wanted if w not in tour and w.rstrip("/") not in tour
               and w not in ("occflownet/__main__.py",)]
    assert not unnamed, f"README tour does not name: {unnamed}"


@pytest.mark.parametrize("pattern", [r"\.\./shared/docs", r"design notes", r"design\.md"])
def test_docs_are_self_contained(pattern):
    files = [*(REPO / "docs").glob("*.md"), REPO / "README.md", *_python_files()]
    files += [p for p in (REPO / "docker").iterdir() if p.is_file()]
    hits = [f"{p.relative_to(REPO)}" for p in files if p != Path(__file__) and re.search(pattern, p.read_text())]
    assert not hits, f"{pattern!r} (outside the repository) in {hits}"


@pytest.mark.parametrize("spelling", [
    r"^INPUTS = ", r"^OUTPUTS = ", r"^METADATA_KEYS = ",              # ONNX contract v1: tensors, metadata
    r"def (validate_calibration|scale_intrinsics|rescale_intrinsics)\(",   # calibration JSON and its rescaling
    r"def (create_session|check_signature)\(",                       # the onnxruntime session and its check
    r"^class ErrorResponse\b", r"def error_response\(",              # the HTTP error shape
    r"def top_down\(",                                                # the top-down picture
])
def test_each_contract_has_one_definition(spelling):
    sources = [p for p in _python_files() if "tests" not in p.relative_to(REPO).parts]
    hits = [f"{p.relative_to(REPO)}: {m.group(0)}" for p in sources
            for m in re.finditer(spelling, p.read_text(), re.MULTILINE)]
    assert len({h.split(": ")[1] for h in hits}) == len(hits) and hits, hits


def test_no_hand_built_error_bodies():
    """Error responses come from the one error shape, never a dict literal with an "error" key."""
    sources = [p for p in _python_files() if "tests" not in p.relative_to(REPO).parts]
    hits = [f"{p.relative_to(REPO)}:{node.lineno}" for p in sources for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, ast.Dict) and any(isinstance(k, ast.Constant) and k.value == "error"
                                                  for k in node.keys)]
    assert not hits, hits


def test_one_atomic_write_idiom():
    """Files appear whole through ``occflownet.files.atomic_path`` only: no other module renames a temporary file
    into place or makes its own temporary file beside the destination."""
    calls = re.compile(r"\b(os\.replace|os\.rename|tempfile\.mkstemp|tempfile\.NamedTemporaryFile)\(")
    package = [p for folder in PACKAGE_DIRS.values() for p in sorted(folder.rglob("*.py"))]
    hits = [f"{p.relative_to(REPO)}: {m.group(1)}" for p in package for m in calls.finditer(p.read_text())]
    assert hits == ["occflownet/files.py: os.replace"], hits


def test_calibration_json_built_in_one_place():
    """Calibration dicts ({"cameras": {name: {"intrinsic", "cam2ego"}}}) come from ``contract.calibration_json``:
    no other dict literal is a calibration camera entry (the viewer's frusta, with more keys, are another format)."""
    package = [p for folder in PACKAGE_DIRS.values() for p in sorted(folder.rglob("*.py"))]
    hits = [str(p.relative_to(REPO)) for p in package for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, ast.Dict)
            and {k.value for k in node.keys if isinstance(k, ast.Constant)} == {"intrinsic", "cam2ego"}]
    assert hits == ["occflownet/contract/calibration.py"], hits


# ----------------------------------------------------------------------------------------------- one predictor path
FEEDS_MODULE = "occflownet/runtime.py"
# Files whose dicts keyed by input names or whose ``.run`` calls are not contract-v1 model feeds, and why.
NOT_MODEL_FEEDS = {
    "occflownet/train/dataset.py": "the training batch (torch tensors for the loss), not an onnxruntime feed",
    "benchmarks/perf/bench_preprocess.py": "feeds the preprocessing sub-graph alone (images, intrinsics → x, k)",
}
NOT_SESSIONS = {"subprocess", "uvicorn", "asyncio"}               # ``X.run(...)`` that runs no model


def _input_names() -> set[str]:
    from occflownet.contract import INPUT_NAMES

    return set(INPUT_NAMES)


def _feed_like(node: ast.AST, names: set[str]) -> bool:
    """A dict literal or ``dict(...)`` call keyed by two or more contract input names whose values are not all dict
    literals (a dict of dicts is a per-input spec, e.g. the dynamic axes of an export), or a dict built over the
    contract's input list (``{s.name: ... for s in INPUTS}``, ``dict(zip(INPUT_NAMES, ...))``, a loop over it that
    assigns ``feeds[spec.name] = ...``)."""
    over_inputs = re.compile(r"\bINPUT(S|_NAMES)\b")
    if isinstance(node, ast.DictComp) or (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                                          and node.func.id == "dict" and node.args):
        return bool(over_inputs.search(ast.unparse(node)))
    if isinstance(node, ast.For) and over_inputs.search(ast.unparse(node.iter)):
        return any(isinstance(t, ast.Subscript) for n in node.body for a in ast.walk(n) if isinstance(a, ast.Assign)
                   for t in a.targets)
    if isinstance(node, ast.Dict):
        keys = [k.value for k in node.keys if isinstance(k, ast.Constant)]
        values = node.values
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict":
        keys = [k.arg for k in node.keywords]
        values = [k.value for k in node.keywords]
    else:
        return False
    return len(names & set(keys)) >= 2 and not all(isinstance(v, ast.Dict) for v in values)


def _runs_a_session(node: ast.AST) -> bool:
    """``X.run(...)`` (onnxruntime ``InferenceSession.run`` and its kin) on anything but subprocess/uvicorn/asyncio."""
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("run", "run_async", "run_with_iobinding", "run_with_ort_values")
            and not (isinstance(node.func.value, ast.Name) and node.func.value.id in NOT_SESSIONS))


def test_one_place_builds_model_feeds_and_runs_sessions():
    """Images + calibration become model feeds in ``occflownet/runtime.py`` only, and only it runs an onnxruntime
    session (docs/layout.md, "One predictor"): no other source file builds a dict keyed by the contract's input
    names or calls ``session.run``."""
    names = _input_names()
    sources = [p for p in _python_files() if "tests" not in p.relative_to(REPO).parts]
    hits = []                                                    # (file, what, line)
    for path in sources:
        rel = str(path.relative_to(REPO))
        if rel in NOT_MODEL_FEEDS:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if _feed_like(node, names):
                hits.append((rel, "builds a feed dict", node.lineno))
            elif _runs_a_session(node):
                hits.append((rel, "runs a session", node.lineno))
    found = {(rel, what) for rel, what, _ in hits}
    assert found == {(FEEDS_MODULE, "builds a feed dict"), (FEEDS_MODULE, "runs a session")}, \
        "\n  ".join(f"{rel}:{line} {what}" for rel, what, line in hits)


def test_intrinsics_are_rescaled_in_one_place():
    """The pixel-centre rescaling rule is applied in ``occflownet/contract/calibration.py`` only (through
    ``Calibration.arrays_for``, which the one feeds function calls): no other source file scales intrinsics."""
    rule = {"scale_intrinsics", "rescale_intrinsics", "resize_matrix"}
    sources = [p for p in _python_files() if "tests" not in p.relative_to(REPO).parts]
    hits = sorted({str(p.relative_to(REPO)) for p in sources for node in ast.walk(ast.parse(p.read_text()))
                   if isinstance(node, ast.Call) and (getattr(node.func, "id", None) in rule
                                                      or getattr(node.func, "attr", None) in rule)})
    assert hits == ["occflownet/contract/calibration.py"], hits
