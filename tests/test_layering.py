"""The package layering, read from every module's imports (module level and inside functions).

- `common` at the bottom; `calibration` and `sync` above it and independent of each other;
  `simulator` above them; `inference` above that; `rig` on top.
- `rig` reaches the simulator only through its simulated devices and `rig/sim/` (SIMULATOR_GATES),
  the demo's own package (`rig/demo/`) and the simulator's own commands (`rig demo`, `rig sim`).
- The live path (camera backends, capture, storage, live server, config, inference.runtime) never
  imports torch or the export tool chain, directly or through anything it imports; the one exception
  is `rig live --device cuda`, whose torch GPU runtime (inference.gpu_runtime) rig.live.app imports
  inside the function that chooses it, never at module level.
- Inside `rig`, its sub-packages (and top-level modules) stand in layers (RIG_LAYERS): each imports
  only its own and those of lower layers, and every one has its place in the table.
- No import cycles between modules, nor between the sub-packages of a package.

The checks are plain functions over an import graph; the last tests feed them a small tree with a
wrong import to show that each check fails when it should.
"""
from __future__ import annotations

import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "calibration", "sync", "simulator", "inference", "rig")
LAYER = {"common": 0, "calibration": 1, "sync": 1, "simulator": 2, "inference": 3, "rig": 4}
SIMULATOR_GATES = ("rig.sim", "rig.cameras.sim", "rig.boards.sim", "rig.truth.simulator",
                   "rig.demo", "rig.commands.demo", "rig.commands.sim")
LIVE_PATH = ("rig.cameras", "rig.capture", "rig.storage", "rig.live", "rig.config", "rig.errors", "inference.runtime")
HEAVY = ("torch", "torchvision", "onnx", "onnxscript")  # training and export only
# rig's sub-packages and top-level modules, bottom to top. The config asks the camera backends what
# they cannot do; the daemons serve cameras and boards; storage writes what capture hands it; live
# shows what capture and storage give; render runs a recorded take through live's model and
# viewpoints; the doctor looks at all of it; the console runs it from a page; the commands drive everything.
RIG_LAYERS = (
    ("rig", "rig.errors"),
    ("rig.progress", "rig.http_access"),
    ("rig.sim", "rig.truth"),  # the simulator as rig sees it; a take's ground truth
    ("rig.cameras", "rig.boards"),  # camera and trigger-board backends, by URI scheme
    ("rig.config",),
    ("rig.daemon",),
    ("rig.storage",),
    ("rig.capture", "rig.calibrate"),  # capture takes the views; calibrate solves from views on disk
    ("rig.live",),
    ("rig.render",),  # a recorded take through the model, outside the live loop
    ("rig.demo",),  # what rig demo builds around the ordinary steps
    ("rig.doctor",),
    ("rig.console",),  # the crew's page over the same library the commands call
    ("rig.commands",),
    ("rig.cli",),
    ("rig.__main__",),
)
# (importer, imported): lazy imports (inside a function) of the live path that may reach torch.
LAZY_GPU_IMPORTS = {("rig.live.app", "inference.gpu_runtime")}


@dataclass
class Graph:
    # module -> {imported project module or third-party top-level name: first line that imports it}
    imports: dict[str, dict[str, int]] = field(default_factory=dict)
    files: dict[str, Path] = field(default_factory=dict)
    # module -> the imports it makes only inside functions (run when called, not when imported)
    lazy: dict[str, set[str]] = field(default_factory=dict)


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(name: str, modules: set[str]) -> str | None:
    """The longest project module that `name` names or lies in (`a.b.c` -> `a.b` if `a.b.c` is a class)."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def _runtime_nodes(tree: ast.AST):
    """Every node but those under `if TYPE_CHECKING:` (imports for annotations only, never run)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            todo.extend(node.orelse)
            continue
        todo.extend(ast.iter_child_nodes(node))


def read_graph(root: Path, packages=PACKAGES) -> Graph:
    graph = Graph()
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            graph.files[_module_name(root, path)] = path
    modules = set(graph.files)
    for mod, path in graph.files.items():
        is_pkg = path.name == "__init__.py"
        found: dict[str, int] = {}
        tree = ast.parse(path.read_text(), str(path))
        in_functions = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                        for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
        eager: set[str] = set()
        for node in _runtime_nodes(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                names = [f"{base}.{a.name}" for a in node.names]  # `from a import b`: a.b if a module, else a
            for name in names:
                target = _resolve(name, modules) or name.split(".")[0]
                if target != mod:
                    found.setdefault(target, node.lineno)
                    if id(node) not in in_functions:
                        eager.add(target)
        graph.imports[mod] = found
        graph.lazy[mod] = set(found) - eager
    return graph


def _package(mod: str) -> str:
    return mod.split(".")[0]


def _within(mod: str, prefixes) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def layer_violations(graph: Graph) -> list[str]:
    out = []
    for mod, targets in graph.imports.items():
        for target, line in targets.items():
            a, b = _package(mod), _package(target)
            if b not in LAYER or a == b:
                continue
            if LAYER[b] >= LAYER[a]:
                out.append(f"{graph.files[mod]}:{line}: {a} (layer {LAYER[a]}) imports {target} (layer {LAYER[b]})")
    return out


def _unit(mod: str) -> str:
    """The sub-package (or top-level module) of a package that `mod` lies in: `rig.capture.session` -> `rig.capture`."""
    return ".".join(mod.split(".")[:2])


def rig_layer_violations(graph: Graph, layers=RIG_LAYERS) -> list[str]:
    level = {unit: i for i, units in enumerate(layers) for unit in units}
    out = []
    for mod, targets in graph.imports.items():
        if _package(mod) != "rig":
            continue
        a = _unit(mod)
        if a not in level:
            out.append(f"{graph.files[mod]}: {a} has no place in RIG_LAYERS")
            continue
        for target, line in targets.items():
            b = _unit(target)
            if _package(target) == "rig" and b != a and b in level and level[b] >= level[a]:
                out.append(f"{graph.files[mod]}:{line}: {a} (layer {level[a]}) imports {target} (layer {level[b]})")
    return out


def subpackage_cycles(graph: Graph) -> list[list[str]]:
    """Cycles between the sub-packages of a package (`inference.train` <-> `inference.evaluate`)."""
    units = Graph()
    for mod, targets in graph.imports.items():
        edges = units.imports.setdefault(_unit(mod), {})
        for target, line in targets.items():
            if target in graph.imports and _package(target) == _package(mod) and _unit(target) != _unit(mod):
                edges.setdefault(_unit(target), line)
    return cycles(units)


def simulator_gate_violations(graph: Graph) -> list[str]:
    return [f"{graph.files[mod]}:{line}: rig imports {target} outside the sim:// backend and the sim commands"
            for mod, targets in graph.imports.items() if _package(mod) == "rig" and not _within(mod, SIMULATOR_GATES)
            for target, line in targets.items() if _package(target) == "simulator"]


def heavy_on_live_path(graph: Graph, allowed=LAZY_GPU_IMPORTS) -> list[str]:
    """Modules of the live path that reach torch/onnx, with the chain of imports that gets there;
    an `allowed` (importer, imported) pair is not followed when the import is inside a function."""
    out = []
    for start in sorted(m for m in graph.imports if _within(m, LIVE_PATH)):
        seen = {start: [start]}
        todo = [start]
        while todo:
            mod = todo.pop()
            for target in graph.imports.get(mod, {}):
                if (mod, target) in allowed and target in graph.lazy.get(mod, ()):
                    continue
                if target in HEAVY:
                    out.append(f"{start} reaches {target}: {' -> '.join(seen[mod] + [target])}")
                elif target in graph.imports and target not in seen:
                    seen[target] = seen[mod] + [target]
                    todo.append(target)
    return sorted(set(out))


def cycles(graph: Graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    counter = 0
    for root in graph.imports:
        if root in index:
            continue
        work = [(root, iter(graph.imports[root]))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in graph.imports:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(graph.imports[child])))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        component.append(m)
                        if m == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


@pytest.fixture(scope="module")
def graph() -> Graph:
    return read_graph(REPO)


def test_lower_packages_never_import_higher_ones(graph):
    assert layer_violations(graph) == []


def test_rig_reaches_the_simulator_only_through_the_sim_backend_and_sim_commands(graph):
    assert simulator_gate_violations(graph) == []


def test_the_live_path_never_imports_torch_or_onnx(graph):
    assert heavy_on_live_path(graph) == []


def test_no_import_cycles(graph):
    assert cycles(graph) == []


def test_rig_sub_packages_import_only_lower_layers(graph):
    assert rig_layer_violations(graph) == []


def test_no_cycles_between_sub_packages(graph):
    assert subpackage_cycles(graph) == []


# ---- the checks themselves fail on a wrong import -------------------------------------------------

def _tree(tmp_path: Path, files: dict[str, str]) -> Graph:
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for pkg in PACKAGES:
        (tmp_path / pkg).mkdir(exist_ok=True)
        (tmp_path / pkg / "__init__.py").touch()
    return read_graph(tmp_path)


def test_a_lower_package_importing_a_higher_one_is_caught(tmp_path):
    g = _tree(tmp_path, {"calibration/solve.py": "def f():\n    from rig.config import load_config\n",
                         "rig/config.py": "def load_config(): ...\n",
                         "sync/clock.py": "from calibration import solve\n"})
    found = layer_violations(g)
    assert len(found) == 2
    assert "calibration (layer 1) imports rig.config (layer 4)" in found[0] + found[1]
    assert "sync (layer 1) imports calibration" in found[0] + found[1]


def test_rig_importing_the_simulator_outside_its_gates_is_caught(tmp_path):
    g = _tree(tmp_path, {"simulator/render.py": "", "rig/cameras/sim.py": "import simulator.render\n",
                         "rig/storage/dataset.py": "from simulator.render import render\n"})
    found = simulator_gate_violations(g)
    assert len(found) == 1 and "rig/storage/dataset.py:1" in found[0]


def test_torch_reached_through_a_chain_from_the_live_path_is_caught(tmp_path):
    g = _tree(tmp_path, {"inference/runtime/pipeline.py": "from inference import helpers\n",
                         "inference/helpers.py": "def f():\n    import torch\n"})
    found = heavy_on_live_path(g)
    assert found == ["inference.runtime.pipeline reaches torch: inference.runtime.pipeline -> inference.helpers -> torch"]


def test_the_gpu_runtime_is_allowed_only_as_the_lazy_import_of_the_live_app(tmp_path):
    gpu = "def f():\n    import torch\n"
    lazy = "def open_model():\n    from inference import gpu_runtime\n"
    g = _tree(tmp_path / "lazy", {"inference/gpu_runtime.py": gpu, "rig/live/app.py": lazy})
    assert heavy_on_live_path(g) == []
    g = _tree(tmp_path / "eager", {"inference/gpu_runtime.py": gpu, "rig/live/app.py": "from inference import gpu_runtime\n"})
    assert heavy_on_live_path(g) == ["rig.live.app reaches torch: rig.live.app -> inference.gpu_runtime -> torch"]
    g = _tree(tmp_path / "other", {"inference/gpu_runtime.py": gpu, "rig/live/engine.py": lazy})
    assert heavy_on_live_path(g) == ["rig.live.engine reaches torch: rig.live.engine -> inference.gpu_runtime -> torch"]


def test_an_import_cycle_is_caught(tmp_path):
    g = _tree(tmp_path, {"calibration/report.py": "from calibration.solve import x\n",
                         "calibration/solve.py": "def g():\n    from calibration.report import y\n"})
    assert cycles(g) == [["calibration.report", "calibration.solve"]]


def test_a_rig_sub_package_importing_a_higher_one_is_caught(tmp_path):
    g = _tree(tmp_path, {"rig/storage/dataset.py": "def f():\n    from rig.capture.session import RigSession\n",
                         "rig/capture/session.py": "from rig.storage import dataset\nclass RigSession: ...\n",
                         "rig/cameras/sim.py": "from rig.boards import sim\n", "rig/boards/sim.py": ""})
    found = rig_layer_violations(g)
    assert len(found) == 2
    assert "rig/storage/dataset.py:2: rig.storage (layer 6) imports rig.capture.session (layer 7)" in found[0] + found[1]
    assert "rig.cameras (layer 3) imports rig.boards.sim (layer 3)" in found[0] + found[1]


def test_a_rig_sub_package_without_a_layer_is_caught(tmp_path):
    g = _tree(tmp_path, {"rig/unplaced/take.py": "from rig.storage import dataset\n", "rig/storage/dataset.py": ""})
    assert [line.split(": ", 1)[1] for line in rig_layer_violations(g)] == ["rig.unplaced has no place in RIG_LAYERS"]


def test_a_cycle_between_sub_packages_is_caught(tmp_path):
    g = _tree(tmp_path, {"inference/train/trainer.py": "def f():\n    from inference.evaluate.model_eval import absrel\n",
                         "inference/train/data.py": "",
                         "inference/evaluate/model_eval.py": "from inference.train.data import FrameSource\n"})
    assert cycles(g) == []  # no module imports itself back: only the sub-packages form a cycle
    assert subpackage_cycles(g) == [["inference.evaluate", "inference.train"]]


def test_imports_for_annotations_only_do_not_count(tmp_path):
    g = _tree(tmp_path, {"calibration/camera.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from rig.config import X\n"})
    assert layer_violations(g) == []


def test_relative_imports_are_resolved(tmp_path):
    g = _tree(tmp_path, {"rig/capture/grab.py": "from ..storage import recorder\nfrom . import session\n",
                         "rig/storage/recorder.py": "", "rig/capture/session.py": ""})
    assert set(g.imports["rig.capture.grab"]) >= {"rig.storage.recorder", "rig.capture.session"}


if __name__ == "__main__":  # print the findings on the real tree
    g = read_graph(REPO)
    found = layer_violations(g) + rig_layer_violations(g) + simulator_gate_violations(g) + heavy_on_live_path(g)
    for line in found + [" <-> ".join(c) for c in cycles(g) + subpackage_cycles(g)]:
        print(line)
    sys.exit(0)
