"""The package layout the README's "Layout" section describes: tiers, no import cycles, no hidden imports.

Read from the source with ``ast`` (nothing is imported): every ``freamer_rl`` import of a module, at the top or inside
a function, must go to its own tier or a lower one; modules form no import cycle; a function-local import is only for
an optional dependency; packages are found by ``pyproject.toml``, never listed by hand.
"""

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "freamer_rl"

#: the README's tiers: a module may import from its own tier and the ones below
TIERS = {
    "errors": 0,
    "torchvision_compat": 0,
    "__init__": 0,
    "config": 1,
    "layers": 1,
    "data": 1,
    "run": 2,
    "model": 3,
    "world_model": 3,
    "machinery": 4,
    "health": 5,
    "trainers": 5,
    "experiments": 6,
    "cli": 7,
}
#: what a function may import locally: optional dependencies (and matplotlib, slow to import, only for pictures)
OPTIONAL = {
    "open_clip",
    "huggingface_hub",
    "transformers",
    "crafter",
    "ray",
    "wandb",
    "tensorboard",
    "matplotlib",
    "torchvision",
    "freamer_rl.layers.clip_backbone",
}  # the last: open_clip's wrapper


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> tuple[set[str], list[tuple[str, int]]]:
    """(every freamer_rl module it imports, [(module, line) of each import inside a function or class body])."""
    tree = ast.parse(path.read_text())
    typing_only = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING"
        for n in ast.walk(node)
    }
    in_function = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        for n in ast.walk(node)
    }
    found, local = set(), []
    own = _module_name(path)
    package = own if path.name == "__init__.py" else own.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        if id(node) in typing_only:  # annotations only: never runs
            continue
        if id(node) in in_function:
            local.append((names[-1], node.lineno))
        found |= {n for n in names if n.startswith("freamer_rl.") or n == "freamer_rl"}
    return found, local


MODULES = {_module_name(p): p for p in sorted(SRC.rglob("*.py"))}


def _resolve(name: str) -> str | None:
    """The module an imported name lives in (``freamer_rl.run.env_registry`` for ``from freamer_rl.run import
    env_registry``), None for a name that is not a module of ours."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _tier(module: str) -> int:
    parts = module.split(".")
    return TIERS[parts[1] if len(parts) > 1 else "__init__"]


GRAPH = {m: {r for n in _imports(p)[0] if (r := _resolve(n)) and r != m} for m, p in MODULES.items()}


def test_every_package_has_a_tier():
    top = {m.split(".")[1] for m in MODULES if "." in m}
    assert top <= set(TIERS), top - set(TIERS)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_tiers(module):
    up = sorted(
        dep for dep in GRAPH[module] if _tier(dep) > _tier(module) and not module.startswith(dep + ".")
    )  # a package's face may import its own modules
    assert not up, f"{module} (tier {_tier(module)}) imports a higher tier: {up}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_function_local_imports_are_optional_dependencies_only(module):
    local = [
        (name, line)
        for name, line in _imports(MODULES[module])[1]
        if name.split(".")[0] not in OPTIONAL and name not in OPTIONAL
    ]
    assert not local, f"{MODULES[module].relative_to(ROOT)}: function-local imports {local}"


def test_no_import_cycle():
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for dep in sorted(GRAPH[m]):
            if m.startswith(dep + "."):  # the package face imported by its own submodule's import machinery
                continue
            if state.get(dep) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(dep) :] + [dep]))
            if dep not in state:
                visit(dep)
        path.pop()
        state[m] = 2

    for m in sorted(GRAPH):
        if m not in state:
            visit(m)


def test_packages_are_found_not_listed():
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "packages" in tool and "find" in tool["packages"], "[tool.setuptools.packages.find]"
    assert (ROOT / "src" / "freamer_rl_envs").resolve() == (ROOT / "envs").resolve()
    # every folder of the library is a package the finder sees
    for folder in SRC.rglob("*"):
        if folder.is_dir() and folder.name != "__pycache__" and any(folder.glob("*.py")):
            assert (folder / "__init__.py").is_file(), f"{folder} has modules but no __init__.py (left out of wheels)"
