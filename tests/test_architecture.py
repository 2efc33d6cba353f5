"""The package's shape: imports run one way, the public API is curated and lazy, every
file is written through one atomic writer."""

from __future__ import annotations

import ast
import functools
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

import emccdcal
from emccdcal._output import atomic_write

SRC = Path(emccdcal.__file__).parent

#: Which subpackages each one may import (besides errors, _util and _output, which all may).
ALLOWED = {
    "model": set(),
    "data": {"model"},
    "fit": {"data", "model"},
    "beads": {"data", "model", "fit", "result"},
    "simulate": {"model", "result"},
    "report": {"data", "model", "fit", "result", "beads", "export"},
    "export": {"data", "model", "result"},
    "acquire": {"data", "model", "fit", "simulate", "result"},
}


@functools.cache
def _tree(path):
    """A source file's syntax tree, parsed once for all the checks here (never mutated)."""
    return ast.parse(path.read_text())


def _imports(path):
    """Package modules a file imports (absolute names), at any depth."""
    tree = _tree(path)
    package = ".".join(("emccdcal",) + path.relative_to(SRC).with_suffix("").parts[:-1])
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            names = [f"{module}.{a.name}" for a in node.names]
            found.update([module, *names])
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m.startswith("emccdcal")}


def _docstring_ids(tree) -> set[int]:
    """The ``id`` of every docstring's constant in a syntax tree (text, not code)."""
    return {
        id(n.body[0].value)
        for n in ast.walk(tree)
        if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
        and n.body
        and isinstance(n.body[0], ast.Expr)
        and isinstance(n.body[0].value, ast.Constant)
    }


def _top(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


@pytest.mark.parametrize("sub", sorted(ALLOWED))
def test_imports_run_one_way(sub):
    allowed = ALLOWED[sub] | {
        sub,
        "errors",
        "defaults",
        "identity",
        "_files",
        "_util",
        "_output",
        "_optimize",
        "_roots",
        "_chebyshev",
        "_xp",
        "_lazy",
        "plugins",
        "",
        "__version__",
    }
    for path in (SRC / sub).rglob("*.py"):
        bad = {m for m in _imports(path) if _top(m) not in allowed}
        assert not bad, f"{path.relative_to(SRC)} imports {sorted(bad)}"


def test_numerics_import_no_argparse_or_pyplot():
    for path in SRC.rglob("*.py"):
        if path.parts[-2] == "cli":
            continue
        tree = _tree(path)
        imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not imported & {"argparse", "matplotlib.pyplot"}, path
        assert "matplotlib.use(" not in path.read_text(), path


def test_import_is_lazy_and_names_resolve():
    code = (
        "import sys, emccdcal; print(sorted(m for m in ('numpy', 'xarray', 'matplotlib') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    for name in emccdcal.__all__:
        assert getattr(emccdcal, name) is not None, name
    assert callable(emccdcal.calibrate) and callable(emccdcal.cots)
    assert emccdcal.noise.__name__ == "emccdcal.model.noise"


def test_a_fresh_interpreter_reaches_every_public_module_after_a_bare_import():
    """``import emccdcal; emccdcal.model.noise.pmf(...)`` as a user types it, nothing
    imported before (the test process has imported them all): every public module, by
    attributes from the top."""
    dotted = [
        ".".join(p.relative_to(SRC.parent).with_suffix("").parts)
        for p in SRC.rglob("*.py")
        if not any(part.startswith("_") for part in p.relative_to(SRC).parts)
        and p.relative_to(SRC).parts[0] in emccdcal._SUBPACKAGES
    ]
    assert "emccdcal.model.noise" in dotted and len(dotted) > 40
    code = (
        "import sys, emccdcal\n"
        "for name in sys.argv[1:]:\n"
        "    module = emccdcal\n"
        "    for part in name.split('.')[1:]:\n"
        "        module = getattr(module, part)\n"
        "    assert module.__name__ == name, name\n"
        "print(len(sys.argv) - 1)\n"
    )
    out = subprocess.run([sys.executable, "-c", code, *dotted], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == str(len(dotted)), out.stderr[-2000:]


def test_no_public_name_hides_a_module():
    modules = {p.stem for p in SRC.glob("*.py")} | {p.name for p in SRC.iterdir() if p.is_dir()}
    assert not set(emccdcal.__all__) & modules
    import emccdcal.calibration as calibration  # the module, not the function

    assert calibration.DEFAULT_BLOCK == 128 and emccdcal.calibrate is calibration.calibrate


def test_atomic_write_uses_the_umask_and_leaves_nothing_on_failure(tmp_path):
    old = os.umask(0o022)
    try:
        path = atomic_write(tmp_path / "a.txt", lambda p: Path(p).write_text("x"))
        assert stat.S_IMODE(path.stat().st_mode) == 0o644
        os.umask(0o027)
        path = atomic_write(tmp_path / "b.txt", lambda p: Path(p).write_text("y"))
        assert stat.S_IMODE(path.stat().st_mode) == 0o640
    finally:
        os.umask(old)

    def fail(p):
        Path(p).write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "a.txt", fail)
    assert (tmp_path / "a.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_dir_shows_the_api_and_its_subpackages_and_the_stub_names_them():
    assert dir(emccdcal) == sorted({*emccdcal.__all__, *emccdcal._SUBPACKAGES})
    packages = {p.parent.name for p in SRC.glob("*/__init__.py")}
    # cli and napari: entry points; _output: private helpers
    assert emccdcal._SUBPACKAGES == packages - {"cli", "napari", "_output"}
    stub = ast.parse((SRC / "__init__.pyi").read_text())
    named = {}
    for node in stub.body:
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                module = "emccdcal" + ("." + node.module if node.module else "")
                named[alias.asname or alias.name] = (module, alias.name)
    for name in emccdcal._SUBPACKAGES:
        assert named.pop(name) == ("emccdcal", name)
    assert set(named) == set(emccdcal._API)
    for name, (module, attribute) in emccdcal._API.items():
        if attribute is None:  # a module: the stub imports it from its parent
            parent, _, leaf = module.rpartition(".")
            assert named[name] == (parent, leaf), name
        else:
            assert named[name] == (module, attribute), name


def test_every_reader_registers_itself_once():
    """The package's readers are its entry points of ``emccdcal.readers`` (as another
    package's would be): every reader module is one, no suffix is claimed twice, and no
    other module lists a format."""
    from emccdcal import plugins
    from emccdcal.data import stacks

    modules = {p.stem for p in (SRC / "data").glob("*.py") if "\nSUFFIXES = " in p.read_text()}
    readers = plugins.load(plugins.READERS)
    own = {
        r.__name__.rsplit(".", 1)[-1]
        for r in readers.values()
        if r.__name__.startswith("emccdcal.")
    }
    assert modules == own
    suffixes = [s for r in readers.values() for s in r.SUFFIXES]
    assert tuple(suffixes) == stacks.STACK_SUFFIXES and len(set(suffixes)) == len(suffixes)
    for reader in readers.values():
        assert callable(reader.header) and callable(reader.settings), reader
    # nothing else lists formats by hand
    for path in SRC.rglob("*.py"):
        if path.name not in {"stacks.py", *(f"{m}.py" for m in own)}:
            assert '".spe"' not in path.read_text(), path


def test_nothing_outside_model_asks_which_register_it_has():
    """No comparison with a register model's name and no ``.cascade`` outside model/:
    code asks the model's ``register`` for what it needs (docs/architecture.md)."""
    from emccdcal.model.noise import EM_MODELS

    found = []
    for path in SRC.rglob("*.py"):
        if path.relative_to(SRC).parts[0] == "model":
            continue
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Compare):
                consts = [c for c in [node.left, *node.comparators] if isinstance(c, ast.Constant)]
                if any(c.value in EM_MODELS for c in consts):
                    found.append(f"{path.relative_to(SRC)}:{node.lineno}")
            if isinstance(node, ast.Attribute) and node.attr == "cascade":
                found.append(f"{path.relative_to(SRC)}:{node.lineno}")
    assert not found, f"branches on the register model: {found}"


def test_no_function_is_longer_than_a_reader_can_hold():
    """No function in src/ over 120 lines of code (docstrings and comments not counted):
    benchmarks/function_lengths.py counts them."""
    import importlib.util

    path = Path(__file__).parents[1] / "benchmarks" / "function_lengths.py"
    spec = importlib.util.spec_from_file_location("function_lengths", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    lengths = module.function_lengths()
    assert len(lengths) > 500  # it found the package's functions
    assert not [where for n, where in lengths if n > 120]


def test_modules_needing_an_extra_are_left_out_of_collection_without_it():
    """A fresh clone's ``make test`` installs ``.[test]`` only: every package module that
    imports a package of another extra at module level must be in the root conftest's
    table, which leaves it out of the doctest collection where that extra is missing."""
    import importlib.metadata
    import importlib.util
    import re

    spec = importlib.util.spec_from_file_location("root_conftest", _source_tree() / "conftest.py")
    root_conftest = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(root_conftest)
    requires = importlib.metadata.requires("emccdcal") or []
    core = {
        re.split(r"[<>=;\[ ]", r, maxsplit=1)[0].lower().replace("-", "_")
        for r in requires
        if "extra ==" not in r
    }
    core |= {"yaml", "tomllib", "tomli", "tomli_w"}  # import names of core distributions
    stdlib = set(sys.stdlib_module_names)
    for path in SRC.rglob("*.py"):
        tree = _tree(path)
        top = {
            a.name.split(".")[0] for n in tree.body if isinstance(n, ast.Import) for a in n.names
        }
        top |= {
            n.module.split(".")[0]
            for n in tree.body
            if isinstance(n, ast.ImportFrom) and n.module and not n.level
        }
        optional = top - stdlib - core - {"emccdcal", "__future__"}
        key = path.relative_to(SRC.parents[1]).as_posix()
        if optional:
            assert key in root_conftest._OPTIONAL, (
                f"{key} imports {sorted(optional)} at module level: add it to the root "
                "conftest's _OPTIONAL (or import them inside the functions that need them)"
            )
            assert set(root_conftest._OPTIONAL[key]) >= optional, key


def test_no_register_model_is_named_outside_model_and_defaults():
    """Every list of register models (CLI choices, the napari dropdown) and every default
    comes from the registry (``defaults.EM_MODELS``, ``DEFAULT_EM_MODEL``,
    ``PAPER_EM_MODEL``): a name typed by hand elsewhere is the next model's bug."""
    import ast

    from emccdcal.defaults import EM_MODELS

    src = Path(__file__).resolve().parents[1] / "src" / "emccdcal"
    found = []
    for path in src.rglob("*.py"):
        rel = path.relative_to(src).as_posix()
        if rel.startswith("model/") or rel == "defaults.py":
            continue
        tree = _tree(path)
        docstrings = _docstring_ids(tree)
        found += [
            f"{rel}:{n.lineno}"
            for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and n.value in EM_MODELS and id(n) not in docstrings
        ]
    assert not found, found


def test_the_engine_has_one_door():
    """Outside fit/, nothing imports the engine, builds its layouts or blocks, calls its
    fit or splits a parameter's name at ``[``: every fit and every expected information
    goes through :class:`emccdcal.fit.series.SeriesLikelihood` (the layouts module's
    method rules, ``check_options`` and ``select_acquisitions``, stay public)."""
    private = {
        "build_layout",
        "layout_of",
        "AcquisitionBlock",
        "Layout",
        "Series",
        "acquisition_estimates",
        "expected_information",
        "e_per_adu_sensitivity",
    }
    found = []
    for path in SRC.rglob("*.py"):
        rel = path.relative_to(SRC).as_posix()
        inside = rel.startswith("fit/")
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
                # a bare name (imported) has no owner; a method of an object is not flagged
                owner = getattr(f.value, "id", "") if isinstance(f, ast.Attribute) else None
                if (
                    not inside
                    and owner in (None, "engine", "layouts")
                    and (name in private or (owner == "engine" and name == "fit"))
                ):
                    found.append(f"{rel}:{node.lineno} calls {name}")
                if (
                    name in ("partition", "split")
                    and node.args
                    and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value == "["
                ):
                    found.append(f"{rel}:{node.lineno} splits a name at '['")
            if (
                not inside
                and isinstance(node, ast.ImportFrom)
                and node.module
                and (
                    node.module.endswith("fit.engine")
                    or (node.module.endswith("fit") and "engine" in {a.name for a in node.names})
                )
            ):
                found.append(f"{rel}:{node.lineno} imports the engine")
    assert not found, found


def test_the_end_to_end_files_named_for_the_fast_loop_exist():
    """conftest.END_TO_END leaves whole files out of ``make test-fast``: a renamed file
    would silently join the fast loop."""
    from conftest import END_TO_END

    here = {p.name for p in Path(__file__).parent.glob("test_*.py")}
    assert END_TO_END <= here, sorted(END_TO_END - here)


LINTED = ["src", "tests", "benchmarks", "examples", "docs/conf.py"]


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=" ".join)
def test_the_code_is_clean_under_the_linter_and_the_formatter(command):
    """``ruff check`` and ``ruff format --check`` (configured in pyproject.toml) find
    nothing in the package, the tests, the benchmarks or the docs' code: CI runs the
    suite, so the suite runs both."""
    import subprocess
    import sys

    pytest.importorskip("ruff")
    root = _source_tree()
    res = subprocess.run(
        [sys.executable, "-m", "ruff", *command, "--no-cache", *LINTED],
        cwd=root,
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, (res.stdout + res.stderr)[-3000:]


@pytest.mark.slow
def test_the_public_api_type_checks(tmp_path):
    """``mypy`` (configured in pyproject.toml: the stub of emccdcal's names and the modules
    they come from) finds nothing."""
    pytest.importorskip("mypy")
    res = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path)],
        cwd=_source_tree(),
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stdout[-3000:]


def _source_tree() -> Path:
    """The repository that holds the package's sources, or a skip where the package is
    installed (a wheel: ``.ci/wheel`` runs the suite against it)."""
    root = SRC.parents[1]
    if not (root / "pyproject.toml").is_file():
        pytest.skip("the package is installed, not in its source tree")
    return root


def test_every_warning_of_the_package_is_an_emccdcal_warning():
    """Each ``warnings.warn`` of the package names its category, and that category is an
    :class:`emccdcal.EmccdcalWarning`: one filter silences them all (a notebook's)."""
    import importlib

    from emccdcal import errors
    from emccdcal.errors import EmccdcalWarning

    calls = 0
    for path in SRC.rglob("*.py"):
        tree = _tree(path)
        name = ".".join(("emccdcal", *path.relative_to(SRC).with_suffix("").parts))
        module = None if "warnings.warn(" not in path.read_text() else importlib.import_module(name)
        for node in ast.walk(tree):
            if not (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "warn"
                and isinstance(node.func.value, ast.Name)
                and node.func.value.id == "warnings"
            ):
                continue
            calls += 1
            given = (
                node.args[1]
                if len(node.args) > 1
                else next((k.value for k in node.keywords if k.arg == "category"), None)
            )
            where = f"{path.relative_to(SRC)}:{node.lineno}"
            assert given is not None, f"{where}: a warning without its category"
            if isinstance(given, ast.Name) and given.id != "category":  # re-raised ones pass
                # at the module's top, or imported where it is used (from emccdcal.errors)
                category = getattr(module, given.id, None) or getattr(errors, given.id)
                assert issubclass(category, EmccdcalWarning), where
    assert calls > 30


def _module_graph() -> dict[str, set[str]]:
    """Module → the package's modules it imports (at any depth: inside functions too)."""
    modules = {}
    for path in SRC.rglob("*.py"):
        name = ".".join(("emccdcal",) + path.relative_to(SRC).with_suffix("").parts)
        modules[name.removesuffix(".__init__")] = path
    graph = {}
    for name, path in modules.items():
        deps = set()
        for imported in _imports(path):
            parts = imported.split(".")  # "pkg.mod.name": the longest that is a module
            found = next(
                (
                    ".".join(parts[:k])
                    for k in range(len(parts), 0, -1)
                    if ".".join(parts[:k]) in modules
                ),
                None,
            )
            if found is not None and found != name:
                deps.add(found)
        graph[name] = deps
    return graph


def test_no_import_goes_round_in_a_circle():
    """No module reaches itself through the modules it imports (imports inside functions
    count: a circle broken only by a late import is a circle all the same)."""
    graph = _module_graph()
    state, circles = {}, []

    def visit(module, trail):
        state[module] = "open"
        for dep in sorted(graph[module]):
            if state.get(dep) == "open":
                circles.append(trail[trail.index(dep) :] + [dep])
            elif dep not in state:
                visit(dep, [*trail, dep])
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert not circles, circles


def _tool_modules():
    return sorted(p for p in (SRC / "export" / "toolfiles").glob("*.py") if p.name != "__init__.py")


@pytest.mark.parametrize("path", _tool_modules(), ids=lambda p: p.stem)
def test_a_tool_module_uses_the_tool_kit_and_no_private_name(path):
    """emccdcal's own tools live by the contract a stranger's must: what they need of the
    package is public (the tool kit, the plug-in's Tool, errors, results), no private
    module nor private name of another module."""
    tree = _tree(path)
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            module = node.module or ""
            if any(part.startswith("_") for part in module.split(".")):
                bad.append(f"from {'.' * node.level}{module} import ...")
            bad += [f"imports {a.name}" for a in node.names if a.name.startswith("_")]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.attr.startswith("_") and not node.attr.startswith("__"):
                bad.append(f"{node.value.id}.{node.attr}")
    own = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}  # its own privates are fine
    bad = [b for b in bad if b.split(".")[0] not in own or "import" in b]
    assert not bad, f"{path.name}: {sorted(set(bad))}"
    assert "toolkit" in {
        a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names
    }


def test_no_tool_is_named_outside_its_own_module():
    """Generic code asks a tool (``Tool.write_modes``, ``all_setpoints``), never tests its
    name: no string constant that is one of emccdcal's own tools' names outside that
    tool's module and defaults.py (docstrings and the names of extras aside)."""
    from emccdcal import plugins

    own = {
        name: tool
        for name, tool in plugins.load(plugins.TOOLS).items()
        if tool.write.__module__.startswith("emccdcal.")
    }
    homes = {name: tool.write.__module__ for name, tool in own.items()}
    found = []
    for path in SRC.rglob("*.py"):
        module = ".".join(("emccdcal",) + path.relative_to(SRC).with_suffix("").parts)
        if path.name == "defaults.py":
            continue
        tree = _tree(path)
        docstrings = _docstring_ids(tree)
        extras = {  # the name of an extra ("fits"), which a tool may share
            id(a)
            for n in ast.walk(tree)
            if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "install_hint"
            for a in n.args
        }
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and id(node) not in docstrings | extras:
                if node.value in homes and homes[node.value] != module:
                    found.append(f"{path.relative_to(SRC)}:{node.lineno}: {node.value!r}")
    assert not found, found


def test_each_thread_fits_with_its_own_compute_context():
    """Where a fit computes and on how many FFT threads is a context of its own thread,
    never module state another thread's fit could change under it (two fits at once
    on one Dask worker)."""
    import threading

    from emccdcal import _xp

    seen, ready = {}, threading.Barrier(2)

    def fit(n):
        with _xp.computing_on("cpu", fft_workers=n):
            ready.wait(timeout=30)  # both inside their blocks at once
            seen[n] = _xp.fft_workers()

    threads = [threading.Thread(target=fit, args=(n,)) for n in (1, 3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen == {1: 1, 3: 3} and _xp.fft_workers() == -1


def test_no_module_outside_model_imports_a_register_implementation():
    """A fit opens the register's tables through the model (``noise.register_tables``),
    a simulation samples through it: no module outside ``model/`` imports an
    implementation (``model.cascade``, ``model._exact``, ``model._gamma``)."""
    implementations = (
        "emccdcal.model.cascade",
        "emccdcal.model.cascade_sampling",
        "emccdcal.model._exact",
        "emccdcal.model._gamma",
    )
    found = {
        str(path.relative_to(SRC)): sorted(
            m for m in _imports(path) if m.startswith(implementations)
        )
        for path in SRC.rglob("*.py")
        if path.relative_to(SRC).parts[0] != "model"
    }
    assert not {k: v for k, v in found.items() if v}


def test_what_a_run_fits_is_decided_in_fit_only():
    """The acquisitions a method fits, its register model and its options, and the model
    halves of its acquisitions, are made by ``fit.series`` (``specify``,
    ``choose_register``, ``acquisition_models``) for every caller: outside ``fit/`` and
    ``model/`` nothing calls ``choose_em_model`` or ``AcquisitionModel`` or uses
    ``layouts``."""
    found = []
    for path in SRC.rglob("*.py"):
        if path.relative_to(SRC).parts[0] in ("fit", "model"):
            continue
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Call):
                name = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
                if name in ("choose_em_model", "AcquisitionModel"):
                    found.append(f"{path.relative_to(SRC)}:{node.lineno}: {name}(")
            elif isinstance(node, ast.Attribute) and getattr(node.value, "id", None) == "layouts":
                found.append(f"{path.relative_to(SRC)}:{node.lineno}: layouts.{node.attr}")
            elif isinstance(node, ast.ImportFrom) and (node.module or "").endswith("layouts"):
                found.append(f"{path.relative_to(SRC)}:{node.lineno}: imports layouts")
    assert not found, found


#: Lines a module of one job stays within (a longer one holds several jobs: split it by
#: them, as calibration/, result/, data/quality/ ... were).
MODULE_LINES = 800


def test_no_module_is_longer_than_one_job():
    over = {
        path.relative_to(SRC).as_posix(): n
        for path in SRC.rglob("*.py")
        if (n := len(path.read_text().splitlines())) > MODULE_LINES
    }
    assert not over, f"modules over {MODULE_LINES} lines: {over}"


#: Every place in the package that deletes a file or a folder, with what makes it only
#: ever delete what a run itself created (never an input, never a user's file or folder).
#: A new deletion fails the test below until it is added here with its reason.
DELETIONS = {
    ("_output/files.py", "atomic_write"): "its own temporary file (a new name of its family)",
    ("_output/verb.py", "_remove_ours"): "a .partial/.old store only with our marker and "
    "nothing else inside; a .tmp file only of our temporary family's name",
    (
        "_output/verb.py",
        "_Staging.add",
    ): "the staged temporary a second write of the same file replaces",
    ("_output/verb.py", "_Staging.discard"): "the staged temporaries of a failed run",
    ("_output/verb.py", "_Lock.release"): "the lock file this run created exclusively",
    ("_output/verb.py", "Output._remove_created"): "the folders this run created, and only "
    "while empty (rmdir)",
    ("_output/verb.py", "Output._publish"): "the output itself, replaced by --overwrite after "
    "the checks that it is no input and no folder emccdcal did not write",
    ("_output/results.py", "write_netcdf"): "its own temporary body file",
    ("acquire/record.py", "_Writing.__init__"): "a store only where zarrs.begun_but_empty "
    "finds it holds no frame and carries this session's marker",
    ("acquire/record.py", "_discard"): "a new session's record, plan and truth, in a "
    "folder _open_session found empty, before any stack was recorded",
    ("cli/db.py", "run"): "a database entry (a row), as `db remove ID` asks; no file",
    ("demo.py", "run_demo"): "the simulated frames in the temporary folder the demo made",
    ("export/_sqlite.py", "_create"): "its own temporary database (a random name)",
    ("runstore.py", "RunStore.discard"): "the output folder where this run made it, only "
    "while empty (rmdir)",
    ("runstore.py", "publish"): "an earlier run's file of the same set, only where "
    "written_by_emccdcal says emccdcal wrote it",
    ("runstore.py", "remove_run"): "tiles and temporaries in a run folder whose "
    "fingerprint emccdcal wrote, by their names; the folder only while empty",
}


def test_every_deletion_is_of_what_a_run_created():
    """Enumerates every call that deletes (``unlink``, ``remove``, ``rmtree``, ``rmdir``)
    in the package: each is in :data:`DELETIONS`, with what keeps it to what the run
    itself created. A new one is reviewed before it lands; one that went is struck off."""
    found = set()
    for path in SRC.rglob("*.py"):
        module = path.relative_to(SRC).as_posix()

        def visit(node, where):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    visit(child, [*where, child.name])
                    continue
                if isinstance(child, ast.Call):
                    name = getattr(child.func, "attr", None) or getattr(child.func, "id", None)
                    if name in ("unlink", "remove", "rmtree", "rmdir", "removedirs"):
                        found.add((module, ".".join(where)))
                visit(child, where)

        visit(_tree(path), [])
    assert found - set(DELETIONS) == set(), f"deletions not reviewed: {found - set(DELETIONS)}"
    assert set(DELETIONS) - found == set(), f"no longer there: {set(DELETIONS) - found}"
