"""The layering of ``mgso`` and ``mgso_kernels``: pyproject.toml's ``[tool.importlinter]`` contracts, and no import
cycle between modules.

Each contract runs in ``lint-imports`` (import-linter, the test extra), one subprocess of this interpreter per contract
(``--contract ID``, no cache), in the folder that holds pyproject.toml, so the packages analysed are that folder's. A
broken contract fails its own test with the contract's name and lint-imports' account of the import chains that break
it. Debt the project knows of is an ``ignore_imports`` entry of the contract it breaks, named to the import.

Import cycles between modules are found here over grimp's import graph (the one import-linter builds; imports inside
functions count): every strongly connected component of more than one module is reported with the imports that close
it. The ``acyclic-siblings`` contract (cycles between the subpackages, or the modules, of one package) holds the
project's one list of known cycles: its ``ignore_imports`` entries are left out of the graph here too.

The negative controls run the same contracts on a copy of the packages with one import added that breaks one
contract, after checking that the copy keeps it, and give the cycle finder a graph with one added import.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mgso", "mgso_kernels")
_LINT = "from importlinter.cli import lint_imports_command; lint_imports_command()"
_INSTALL = "import-linter is not installed: pip install -e '.[test]' (pyproject.toml's test extra)"


def _contract_options(pyproject: Path) -> list[dict]:
    """The options of every contract in ``[tool.importlinter]``, as written."""
    try:
        import tomllib
    except ImportError:  # Python 3.10: import-linter depends on tomli there
        try:
            import tomli as tomllib
        except ImportError:
            return []
    with open(pyproject, "rb") as f:
        config = tomllib.load(f)
    return list(config.get("tool", {}).get("importlinter", {}).get("contracts", []))


CONTRACTS = [(str(c.get("id", "")), str(c.get("name", ""))) for c in _contract_options(ROOT / "pyproject.toml")]
NAMES = dict(CONTRACTS)
CYCLES_CONTRACT = "acyclic-siblings"


def _require_import_linter() -> None:
    if importlib.util.find_spec("importlinter") is None:
        pytest.fail(_INSTALL, pytrace=False)


def lint_imports(root: Path, contract: str) -> subprocess.CompletedProcess:
    """``lint-imports --no-cache --contract CONTRACT`` in ``root`` (which holds pyproject.toml and the packages)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [env.get("PYTHONPATH")])])
    env["NO_COLOR"] = "1"
    env["COLUMNS"] = "200"
    return subprocess.run([sys.executable, "-c", _LINT, "--no-cache", "--contract", contract], cwd=root, env=env,
                          capture_output=True, text=True, timeout=300)


_BANNER = set("╔╗╚╝║╣╠╦╩╬═─│└┘▶◀▲")


def _report(proc: subprocess.CompletedProcess) -> str:
    """lint-imports' account of a broken contract (its banner and summary left out)."""
    out = proc.stdout + proc.stderr
    at = out.find("Broken contracts")
    if at >= 0:
        return out[at:].strip()
    # not a broken chain: a configuration error or an ignore_imports entry that matches nothing
    lines = [ln for ln in out.splitlines() if not _BANNER & set(ln)]
    text = "\n".join(lines).strip()
    if "No matches for ignored import" in text:
        text += "\n(the import is gone: remove its entry from the contract's ignore_imports)"
    return text


def check_contract(root: Path, contract: str) -> None:
    """Fail, naming the contract, when lint-imports finds it broken (or cannot check it) in ``root``."""
    proc = lint_imports(root, contract)
    if proc.returncode != 0:
        pytest.fail(f"import contract '{NAMES.get(contract, contract)}' ({contract}, pyproject.toml "
                    f"[tool.importlinter]) is broken:\n{_report(proc)}", pytrace=False)


# ------------------------------------------------------------------------------------------------ the contracts
def test_contracts_are_declared():
    _require_import_linter()
    assert CONTRACTS, "pyproject.toml has no [[tool.importlinter.contracts]]"
    missing = [name for cid, name in CONTRACTS if not cid]
    assert not missing, f"contracts without an id (lint-imports --contract needs one): {missing}"


def kernel_modules_left_out(package: Path, contracts: list[dict]) -> dict[str, list[str]]:
    """The modules and subpackages of ``mgso_kernels`` (at ``package``) that a per-module contract does not name:
    the layers of ``kernels-layers`` and the kernels that ``twins-apart`` keeps from the twins. Those contracts list
    the modules by hand, so a new one left off would go unchecked."""
    names = sorted({p.stem for p in package.glob("*.py") if p.stem != "__init__"}
                   | {p.name for p in package.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
                   - {"reference"})
    by_id = {c.get("id"): c for c in contracts}
    layered = {m.strip() for layer in by_id.get("kernels-layers", {}).get("layers", []) for m in layer.split("|")}
    kept_apart = {m.rsplit(".", 1)[-1] for m in by_id.get("twins-apart", {}).get("forbidden_modules", [])}
    left = {"kernels-layers": [n for n in names if n not in layered],
            "twins-apart": [n for n in names if n not in kept_apart]}
    return {k: v for k, v in left.items() if v}


def test_every_kernel_module_is_in_the_contracts_that_list_them(tmp_path):
    """Issue 44: a module of mgso_kernels left off the hand-written lists would be silently unchecked."""
    contracts = _contract_options(ROOT / "pyproject.toml")
    left = kernel_modules_left_out(ROOT / "mgso_kernels", contracts)
    assert not left, f"modules of mgso_kernels that pyproject.toml's contracts do not name: {left}"
    # the control: a copy of the package with one more module is caught by both lists
    copy = tmp_path / "mgso_kernels"
    shutil.copytree(ROOT / "mgso_kernels", copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "new_kernel.py").write_text("")
    assert kernel_modules_left_out(copy, contracts) == {"kernels-layers": ["new_kernel"],
                                                        "twins-apart": ["new_kernel"]}


@pytest.mark.parametrize("contract", [cid for cid, _ in CONTRACTS])
def test_contract_kept(contract):
    _require_import_linter()
    check_contract(ROOT, contract)


# ----------------------------------------------------------------------------------------- cycles, over grimp
def import_cycles(graph) -> list[list[str]]:
    """The strongly connected components of more than one module of a grimp import graph (Tarjan, iterative)."""
    adj = {m: sorted(graph.find_modules_directly_imported_by(m)) for m in sorted(graph.modules)}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    for start in adj:
        if start in index:
            continue
        work = [(start, 0)]
        while work:
            v, i = work.pop()
            if i == 0:
                index[v] = low[v] = len(index)
                stack.append(v)
                on_stack.add(v)
            succ = adj.get(v, [])
            while i < len(succ) and succ[i] in index:
                w = succ[i]
                if w in on_stack:
                    low[v] = min(low[v], index[w])
                i += 1
            if i < len(succ):
                work.append((v, i + 1))
                work.append((succ[i], 0))
                continue
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    cycles.append(sorted(comp))
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[v])
    return sorted(cycles)


def describe_cycle(graph, modules: list[str]) -> str:
    """The imports inside one cycle, one a line: ``importer -> imported (l.N: the line)``."""
    inside = set(modules)
    lines = []
    for m in modules:
        for imported in sorted(graph.find_modules_directly_imported_by(m)):
            if imported not in inside:
                continue
            details = graph.get_import_details(importer=m, imported=imported)
            where = "; ".join(f"l.{d['line_number']}: {d['line_contents']}" for d in details) or "added import"
            lines.append(f"  {m} -> {imported} ({where})")
    return "\n".join(lines)


def known_cycle_imports(pyproject: Path) -> list[tuple[str, str]]:
    """The ``ignore_imports`` entries of the acyclic-siblings contract, as (importer, imported)."""
    options = {str(c.get("id")): c for c in _contract_options(pyproject)}
    entries = []
    for entry in options.get(CYCLES_CONTRACT, {}).get("ignore_imports", []):
        importer, _, imported = (part.strip() for part in str(entry).partition("->"))
        assert "*" not in entry and importer and imported, (
            f"pyproject.toml, contract '{CYCLES_CONTRACT}': ignore_imports entry {entry!r}: write it as "
            f"'package.module -> package.module' (no wildcard), which tests/test_layering.py reads too")
        entries.append((importer, imported))
    return entries


def _graph():
    _require_import_linter()  # grimp comes with it
    import grimp

    return grimp.build_graph(*PACKAGES, cache_dir=None)


def test_no_import_cycle_between_modules():
    graph = _graph()
    modules = graph.modules
    for importer, imported in known_cycle_imports(ROOT / "pyproject.toml"):
        if {importer, imported} <= modules and graph.direct_import_exists(importer=importer, imported=imported):
            graph.remove_import(importer=importer, imported=imported)
    cycles = import_cycles(graph)
    assert not cycles, (
        f"import cycles between modules (pyproject.toml's contract '{CYCLES_CONTRACT}' lists the known ones):\n"
        + "\n".join(f"cycle of {len(c)} modules:\n{describe_cycle(graph, c)}" for c in cycles))


# ---------------------------------------------------------------------------------------- negative controls
def test_cycle_finder_on_a_small_graph():
    _require_import_linter()
    import grimp

    g = grimp.ImportGraph()
    for a, b in (("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.c", "p.d"), ("p.e", "p.d"), ("p.f", "p.g"),
                 ("p.g", "p.f")):
        g.add_import(importer=a, imported=b)
    assert import_cycles(g) == [["p.a", "p.b", "p.c"], ["p.f", "p.g"]]


def test_cycle_finder_sees_an_import_added_to_the_real_graph():
    graph = _graph()
    splat = "mgso_kernels.splat."
    assert not [c for c in import_cycles(graph) if any(m.startswith(splat) for m in c)]
    # common.py is what raster.py, raster_bwd.py and raster_tile.py import: one import back closes a circle
    graph.add_import(importer=splat + "common", imported=splat + "raster_bwd")
    cycles = [c for c in import_cycles(graph) if any(m.startswith(splat) for m in c)]
    assert len(cycles) == 1
    assert {splat + "common", splat + "raster_bwd"} <= set(cycles[0])
    text = describe_cycle(graph, cycles[0])
    assert "mgso_kernels.splat.common -> mgso_kernels.splat.raster_bwd (added import)" in text
    assert "mgso_kernels.splat.raster_bwd -> mgso_kernels.splat.common (l." in text


def _copy_tree(dst: Path) -> Path:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, dst / pkg, ignore=ignore)
    shutil.copy2(ROOT / "pyproject.toml", dst / "pyproject.toml")
    return dst


# (contract, file of the copy, the line added to it (the file made when missing), the import lint-imports must name)
PROBES = [
    ("kernels-standalone", "mgso_kernels/image.py", "from mgso import geometry", "mgso_kernels.image -> mgso.geometry"),
    # a module of the application wing (mgso/app/ made a package in the copy if it is not one yet)
    ("domain-not-app", "mgso/app/_probe_wing.py", "", None),
    ("domain-not-app", "mgso/geometry.py", "from mgso.app import _probe_wing", "mgso.geometry -> mgso.app._probe_wing"),
    ("domain-not-app", "mgso/system.py", "from mgso.app import writer", "mgso.system -> mgso.app.writer"),
    # the odometry importing the map again (the messages lived in mgso.mapping until 2026-12-05)
    ("odometry-not-map", "mgso/loop/graph.py", "from mgso.mapping import messages",
     "mgso.loop.graph -> mgso.mapping.messages"),
    ("kernels-layers", "mgso_kernels/runtime.py", "from . import image", "mgso_kernels.runtime -> mgso_kernels.image"),
    ("kernels-layers", "mgso_kernels/adam.py", "from .splat import Rasterizer",
     "mgso_kernels.adam -> mgso_kernels.splat"),
    ("twins-apart", "mgso_kernels/reference/image.py", "from .. import image",
     "mgso_kernels.reference.image -> mgso_kernels.image"),
    ("kernels-not-twins", "mgso_kernels/track.py", "from .reference import track",
     "mgso_kernels.track -> mgso_kernels.reference.track"),
    # the circle of splat's raster modules, as it was
    ("splat-layers", "mgso_kernels/splat/raster_tile.py", "from .raster_bwd import rasterize_backward",
     "mgso_kernels.splat.raster_tile -> mgso_kernels.splat.raster_bwd"),
    # import-linter names the import(s) whose removal breaks the cycle: either side of it
    ("acyclic-siblings", "mgso/eval/ate.py", "from mgso.mapping import gaussian_map",
     (".eval -> .mapping", ".mapping -> .eval")),
]


def _append(path: Path, line: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    init = path.parent / "__init__.py"
    if not init.exists():
        init.write_text("")
    path.write_text((path.read_text() if path.exists() else "") + f"\n{line}  # layering probe\n")


PROBE_CASES = [p for p in PROBES if p[3] is not None]


@pytest.mark.parametrize("contract,path,line,named", PROBE_CASES, ids=[f"{c}:{p}" for c, p, _, _ in PROBE_CASES])
def test_contract_breaks_on_an_added_import(tmp_path, contract, path, line, named):
    _require_import_linter()
    assert contract in NAMES, f"no contract '{contract}' in pyproject.toml"
    root = _copy_tree(tmp_path)
    for c, p, ln, n in PROBES:  # the modules a probe imports
        if n is None and c == contract:
            _append(root / p, ln)
    check_contract(root, contract)  # the copy keeps it, as the tree does
    _append(root / path, line)
    with pytest.raises(pytest.fail.Exception) as failed:
        check_contract(root, contract)
    message = str(failed.value)
    assert f"import contract '{NAMES[contract]}' ({contract}" in message
    named = (named,) if isinstance(named, str) else named
    assert any(n in message for n in named), message


def test_a_stale_ignore_entry_is_reported(tmp_path):
    """An ignore_imports entry whose import has gone fails the contract, saying so (the debt list stays true)."""
    _require_import_linter()
    root = _copy_tree(tmp_path)
    config = root / "pyproject.toml"
    text = config.read_text()
    entry = '"mgso_kernels.reference.select -> mgso_kernels.select",'
    assert entry in text
    config.write_text(text.replace(entry, entry + '\n    "mgso_kernels.reference.image -> mgso_kernels.image",'))
    with pytest.raises(pytest.fail.Exception) as failed:
        check_contract(root, "twins-apart")
    message = str(failed.value)
    assert "No matches for ignored import mgso_kernels.reference.image -> mgso_kernels.image" in message
    assert "remove its entry" in message
    assert not _BANNER & set(message)


def test_known_cycles_are_what_the_cycle_test_leaves_out(tmp_path):
    """The cycle test's allowance is the acyclic-siblings contract's list: an import added to a copy of the packages
    that closes a cycle fails the test's check, and listing it in the contract lets it through."""
    _require_import_linter()
    entries = known_cycle_imports(ROOT / "pyproject.toml")
    assert ("mgso.io.ply", "mgso.mapping.gaussian_map") in entries
    config = tmp_path / "pyproject.toml"
    shutil.copy2(ROOT / "pyproject.toml", config)
    text = config.read_text()
    anchor = '"mgso.io.ply -> mgso.mapping.gaussian_map",'
    config.write_text(text.replace(anchor, anchor + '\n    "mgso.geometry -> mgso.camera",'))
    assert ("mgso.geometry", "mgso.camera") in known_cycle_imports(config)
    config.write_text(text.replace(anchor, anchor + '\n    "mgso.io.* -> mgso.mapping",'))
    with pytest.raises(AssertionError, match="no wildcard"):
        known_cycle_imports(config)


# --------------------------------------------------------------------------------------------- class names
def class_names(root: Path) -> dict[str, list[str]]:
    """Top-level class name -> the modules (``path:line``) that define it, over mgso and mgso_kernels."""
    import ast

    found: dict[str, list[str]] = {}
    for pkg in ("mgso", "mgso_kernels"):
        for path in sorted((root / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            for node in tree.body:
                if isinstance(node, ast.ClassDef):
                    found.setdefault(node.name, []).append(f"{path.relative_to(root)}:{node.lineno}")
    return found


def test_no_two_classes_share_a_name():
    """Issue 14: Odometry, PointCloud, RefineResult and MarginalizedPoints each named two classes; a reader (and an
    import) could take one for the other."""
    shared = {n: where for n, where in class_names(ROOT).items() if len(where) > 1}
    assert not shared, f"classes that share a name: {shared}"


def test_shared_class_names_are_found(tmp_path):
    """The check above on a copy with one name defined twice (negative control)."""
    for pkg in ("mgso", "mgso_kernels"):
        (tmp_path / pkg).mkdir()
    (tmp_path / "mgso" / "a.py").write_text("class Thing:\n    pass\n")
    (tmp_path / "mgso_kernels" / "b.py").write_text("x = 1\n\n\nclass Thing:\n    pass\n")
    assert class_names(tmp_path)["Thing"] == ["mgso/a.py:1", "mgso_kernels/b.py:4"]
