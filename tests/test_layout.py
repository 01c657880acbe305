"""The package's shape (issue 12): no import cycles in hitops; wrap tracking small enough to read.

The import graph is built from the source with ``ast`` (every ``import`` and
``from ... import``, at module level or inside functions: a lazy import that
closes a cycle is still a cycle in the design).  ``from pkg import name``
depends on the submodule ``pkg.name`` when there is one, else on ``pkg``; a
module's own parent packages are not dependencies (Python imports them first
whatever the module does).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path


ROOT = Path(__file__).resolve().parent.parent / "hitops"
#: issue 12: no module of hitops/tracking or of the calibrate pipeline over ~400 lines, no
#: function over ~80
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80
#: issue 25: every module of the packages below, subpackages included, none excepted
WING_MODULE_LINES = 450
WING_FUNCTION_LINES = 100
WING_PACKAGES = ("calibrate", "tracking", "kernels", "io")


def _modules():
    """{dotted name: (path, is_package)} of every module of hitops."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _imports(name, path, is_pkg, modules):
    """The hitops modules ``name`` imports."""
    package = name if is_pkg else name.rsplit(".", 1)[0]
    deps = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[:len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                       for a in node.names]
        else:
            continue
        deps.update(t for t in targets
                    if t in modules and t != name and not name.startswith(t + "."))
    return deps


def import_graph():
    modules = _modules()
    return {name: _imports(name, path, is_pkg, modules) for name, (path, is_pkg) in modules.items()}


def cycles(graph):
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_in_hitops():
    graph = import_graph()
    assert "hitops.tracking.smooth" in graph and graph["hitops.tracking.antenna"]
    assert cycles(graph) == []


#: the calibrate pipeline's stages (api -> inputs -> plan -> pipeline -> report, with the
#: modules they call): held to the same limits as hitops/tracking
PIPELINE_MODULES = ("api", "inputs", "plan", "tracking_setup", "band_index", "chunk_read", "pipeline",
                    "n0/step", "report", "transfer", "output", "groups", "memory", "chunks")


def _too_long(paths, max_module=MAX_MODULE_LINES, max_function=MAX_FUNCTION_LINES):
    too_long = []
    for path in paths:
        text = path.read_text()
        if len(text.splitlines()) > max_module:
            too_long.append(f"{path.name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > max_function:
                    too_long.append(f"{path.name}: {node.name}() {lines} lines")
    return too_long


def test_the_size_check_sees_a_long_function(tmp_path):
    long = tmp_path / "long.py"
    long.write_text("def f():\n" + "    x = 1\n" * MAX_FUNCTION_LINES)
    assert _too_long([long]) == [f"long.py: f() {MAX_FUNCTION_LINES + 1} lines"]


def test_calibrate_pipeline_modules_and_functions_are_small():
    paths = [ROOT / "calibrate" / f"{name}.py" for name in PIPELINE_MODULES]
    assert all(p.exists() for p in paths)
    assert _too_long(paths) == []


def test_tracking_modules_and_functions_are_small():
    assert _too_long(sorted((ROOT / "tracking").glob("*.py"))) == []


def test_every_module_of_the_calibrate_wing_is_small():
    """calibrate/ (n0/ included), tracking/, kernels/ and io/: no module over 450 lines, no
    function over 100, and no exception list."""
    paths = sorted(p for name in WING_PACKAGES for p in (ROOT / name).rglob("*.py"))
    assert len(paths) > 40
    assert _too_long(paths, WING_MODULE_LINES, WING_FUNCTION_LINES) == []


def test_wrap_tracking_lives_in_hitops_tracking():
    """The kernels sit beside their trackers; simulate and calibrate share hitops/geometry.py."""
    graph = import_graph()
    for gone in ("hitops.kernels.tracking", "hitops.kernels.antenna"):
        assert gone not in graph
    calibrate_side = [n for n in graph if n.startswith(("hitops.calibrate", "hitops.tracking"))]
    assert not [n for n in calibrate_side if "hitops.simulate.geometry" in graph[n]]
    assert "hitops.geometry" in graph["hitops.simulate.geometry"]


# issue 36: one Measurement Set access layer.  casacore tables (Measurement Sets v2 and CASA
# calibration tables) are opened only in hitops/io/ (hitops/io/tables.py for everything
# outside its own readers), so that a second backend (MSv4 processing sets) has one seam to
# stand beside; the CASA task wrappers and the test support are outside the rule.
TABLE_OPENERS_ALLOWED = ("io", "casa", "testing")
#: casacore.tables (and dask-ms, which opens casacore tables) functions that open or make a table
TABLE_CALLS = {"table", "taql", "tablecommand", "tableexists", "default_ms", "default_ms_subtable",
               "tablefromascii", "msconcat", "makearrcoldesc", "maketabdesc",
               "xds_from_ms", "xds_from_table", "xds_to_table"}
def table_opens(path):
    """'line: what' of every casacore table open (import or call) in the module at ``path``."""
    imports, calls = [], []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [f"{node.module}.{a.name}" for a in node.names] if node.module else []
        elif isinstance(node, ast.Call):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if called in TABLE_CALLS:
                calls.append((node.lineno, f"{called}()"))
            continue
        else:
            continue
        imports += [(node.lineno, f"import {n}") for n in names
                    if n.startswith(("casacore.tables", "daskms")) or n == "casacore"]
    # a bare table(...) or x.table(...) is casacore's only where casacore is imported; the
    # other names are casacore's or dask-ms's alone
    calls = [(line, what) for line, what in calls if what != "table()" or imports]
    return [f"{line}: {what}" for line, what in sorted(imports + calls)]


def test_the_open_finder_sees_an_open(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f(ms):\n    from casacore import tables as pt\n"
                      "    with pt.table(ms) as t:\n        return t.nrows()\n"
                      "def g(ms):\n    import daskms\n    return daskms.xds_from_ms(ms)\n")
    assert table_opens(module) == ["2: import casacore.tables", "3: table()",
                                   "6: import daskms", "7: xds_from_ms()"]
    module.write_text("from casacore import measures\ndef f(x):\n    return x.table(1)\n")
    assert table_opens(module) == []


def test_casacore_tables_are_opened_only_in_hitops_io():
    opens = {}
    for path in sorted(ROOT.rglob("*.py")):
        relative = path.relative_to(ROOT).as_posix()
        if relative.split("/")[0] in TABLE_OPENERS_ALLOWED:
            continue
        found = table_opens(path)
        if found:
            opens[relative] = found
    assert opens == {}, "open casacore tables through hitops/io/tables.py or metadata.py"


def test_inside_hitops_io_one_module_opens_casacore_tables_and_one_opens_dask_ms():
    """hitops/io/tables.py holds python-casacore's table calls, hitops/io/read.py dask-ms's:
    the two places a second backend stands beside."""
    daskms = ("import daskms", "xds_from_ms()", "xds_from_table()", "xds_to_table()")
    opens = {}
    for path in sorted((ROOT / "io").rglob("*.py")):
        relative = path.relative_to(ROOT).as_posix()
        for found in table_opens(path):
            is_daskms = found.split(": ", 1)[1].startswith(daskms)
            if relative != ("io/read.py" if is_daskms else "io/tables.py"):
                opens.setdefault(relative, []).append(found)
    assert table_opens(ROOT / "io" / "tables.py")
    assert opens == {}


# ---- issue 36: no long parameter lists where the pipeline passes its types down
MAX_PARAMETERS = 12
PARAMETER_PACKAGES = ("calibrate", "solutions", "tracking", "io")


def _long_signatures(paths, limit=MAX_PARAMETERS):
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                if names and names[0] in ("self", "cls"):
                    names = names[1:]
                if len(names) > limit:
                    found.append(f"{path.name}: {node.name}() {len(names)} parameters")
    return found


def test_the_parameter_check_sees_a_long_signature(tmp_path):
    wide = tmp_path / "wide.py"
    wide.write_text("def f(" + ", ".join(f"a{i}" for i in range(MAX_PARAMETERS + 1)) + "):\n"
                    "    pass\n\nclass C:\n    def g(self, " +
                    ", ".join(f"a{i}" for i in range(MAX_PARAMETERS)) + "):\n        pass\n")
    assert [s.split(": ")[1] for s in _long_signatures([wide])] == [f"f() {MAX_PARAMETERS + 1} parameters"]


def test_no_function_of_the_calibrate_wing_takes_more_than_twelve_parameters():
    paths = sorted(p for name in PARAMETER_PACKAGES for p in (ROOT / name).rglob("*.py"))
    assert _long_signatures(paths) == []


# ---- one stage numbering (hitops/calibrate/stages.py) in the code and the docs
def _stage_claims(path: Path):
    """The stage numbers a module's docstring claims ("Stage 3 of", "Stages 4-5 of")."""
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    match = re.match(r"Stages? (\d+)(?:-(\d+))? of ``hitops calibrate``", doc)
    if not match:
        return None
    first = int(match.group(1))
    return set(range(first, int(match.group(2) or first) + 1))


def test_stage_numbers_of_the_modules_are_the_declared_ones():
    from hitops.calibrate.stages import STAGES

    declared = {}
    for info in STAGES:
        for module in info.modules:
            declared.setdefault(module, set()).add(int(info.stage))
    checked = 0
    for path in sorted((ROOT / "calibrate").rglob("*.py")):
        claims = _stage_claims(path)
        relative = f"hitops/{path.relative_to(ROOT)}"
        if claims is not None:
            assert relative in declared, f"{relative} claims stage(s) {claims} but no stage lists it"
            assert claims == declared[relative], (f"{relative}: docstring says stage(s) "
                                                  f"{sorted(claims)}, stages.py {sorted(declared[relative])}")
            checked += 1
    assert checked >= 5
    assert [int(i.stage) for i in STAGES] == list(range(1, len(STAGES) + 1))


def test_the_docs_stage_table_is_the_declared_one():
    from hitops.calibrate.stages import STAGES

    text = (ROOT.parent / "docs" / "architecture.md").read_text()
    rows = re.findall(r"^\| (\d+)\. ([a-z0-9 ]+) \|", text, flags=re.M)
    assert [(int(n), name) for n, name in rows] == [
        (int(i.stage), i.stage.name.lower().replace("_", " ")) for i in STAGES]


def test_the_docs_mode_table_is_the_declared_one():
    from hitops.calibrate.modes import REFUSED

    text = (ROOT.parent / "docs" / "calibrate.md").read_text()
    rows = dict(re.findall(r"^\| (visibilities|table|calibrator) \| (.*) \|$", text, flags=re.M))
    assert {mode.value: "; ".join(r.option for r in refused)
            for mode, refused in REFUSED.items()} == rows
