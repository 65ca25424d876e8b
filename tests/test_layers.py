"""The package's layers (DESIGN.md, architecture): the core imports nothing from the lab,
and no module reaches into another's private names.

Read from the source with ``ast``, so an import inside a function counts as much as one
at the top of a module, and nothing is executed.
"""

import ast
from pathlib import Path

import pytest

import markerpose

ROOT = Path(markerpose.__file__).parent
PACKAGE = "markerpose"
# The lab: experiments, the peers comparison, training and the renderer. The CLI sits
# above everything (it may import the lab, lazily); nothing below imports it.
LAB = ("experiments", "peers", "train", "synth")
ABOVE_CORE = LAB + ("cli",)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package_of(path: Path) -> str:
    """The package that a relative import in ``path`` starts from."""
    name = _module_name(path)
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _all_modules() -> list[Path]:
    return sorted(p for p in ROOT.rglob("*.py") if "__pycache__" not in p.parts)


def _is_core(path: Path) -> bool:
    top = path.relative_to(ROOT).parts[0]
    return top.removesuffix(".py") not in ABOVE_CORE


def _imports(path: Path, source: str | None = None):
    """Every import in ``path`` (or in ``source``, read as if it were ``path``), at any
    depth: (line, module, names). ``module`` is the absolute module name; ``names`` what a
    ``from`` import takes from it (empty for a plain ``import``).
    ``importlib.import_module("...")`` with a literal name counts too."""
    source = path.read_text(encoding="utf-8") if source is None else source
    tree = ast.parse(source, filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = _package_of(path).split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield node.lineno, module, tuple(a.name for a in node.names)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and not node.args[0].value.startswith(".")
        ):
            yield node.lineno, node.args[0].value, ()


def _reaches(module: str, names: tuple, layers: tuple) -> str | None:
    """The first of ``layers`` (subpackages of markerpose) that importing ``names`` from
    ``module`` reaches, or None. ``from markerpose import synth`` reaches synth too."""
    targets = [module] + [f"{module}.{n}" for n in names if n != "*"]
    for target in targets:
        parts = target.split(".")
        if parts[0] == PACKAGE and len(parts) > 1 and parts[1] in layers:
            return parts[1]
    return None


CORE = [p for p in _all_modules() if _is_core(p)]


def test_the_core_is_found():
    names = {_module_name(p) for p in CORE}
    assert {"markerpose.calibration", "markerpose.camera", "markerpose.ultrasound.recording"} <= names
    assert not any(n.split(".")[1] in ABOVE_CORE for n in names if "." in n)


@pytest.mark.parametrize("path", CORE, ids=lambda p: _module_name(p))
def test_core_imports_nothing_from_the_lab(path):
    bad = [
        f"{path.relative_to(ROOT.parent)}:{line}: imports {module}{' (' + ', '.join(names) + ')' if names else ''} from the {layer}"
        for line, module, names in _imports(path)
        if (layer := _reaches(module, names, ABOVE_CORE))
    ]
    assert not bad, "the core must not import the lab or the CLI:\n" + "\n".join(bad)


@pytest.mark.parametrize("path", _all_modules(), ids=lambda p: _module_name(p))
def test_no_private_names_across_modules(path):
    own = _module_name(path)
    bad = []
    for line, module, names in _imports(path):
        if module.split(".")[0] != PACKAGE or module == own:
            continue
        for name in names:
            if name.startswith("_") and not (name.startswith("__") and name.endswith("__")):
                bad.append(f"{path.relative_to(ROOT.parent)}:{line}: from {module} import {name}")
    assert not bad, "private names stay in their module (make the name public, with a docstring):\n" + "\n".join(bad)


def test_the_checks_see_relative_and_nested_imports():
    src = (
        "import numpy\n"
        "def f():\n"
        "    from ..synth.render import _expose\n"
        "    from .. import experiments\n"
        "    from .probe import invert\n"
        "    import importlib\n"
        "    importlib.import_module('markerpose.train.loop')\n"
    )
    found = [(m, n) for _, m, n in _imports(ROOT / "ultrasound" / "recording.py", src)]
    assert found == [
        ("numpy", ()),
        ("markerpose.synth.render", ("_expose",)),
        ("markerpose", ("experiments",)),
        ("markerpose.ultrasound.probe", ("invert",)),
        ("importlib", ()),
        ("markerpose.train.loop", ()),
    ]
    assert [_reaches(m, n, LAB) for m, n in found] == [None, "synth", "experiments", None, None, "train"]
    # In a package's __init__, "." is the package itself.
    assert [m for _, m, _ in _imports(ROOT / "ultrasound" / "__init__.py", "from .probe import x\n")] == ["markerpose.ultrasound.probe"]
