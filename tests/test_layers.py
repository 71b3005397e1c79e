"""Which module may import which: the import-linter contracts of pyproject.toml hold on the tree
and catch a wrong import, and no module imports another package's private modules."""

import ast
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The trees the private-module rule covers; tests/ may import private modules to test them.
CHECKED = ("diffeit", "hw", "benchmarks", "examples")


def _lint_imports(cwd: Path) -> subprocess.CompletedProcess:
    """`lint-imports` on the packages under `cwd` (it puts `cwd` first on sys.path)."""
    command = [sys.executable, "-c", "from importlinter.cli import lint_imports_command; lint_imports_command()"]
    return subprocess.run([*command, "--no-cache"], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_the_tree_keeps_every_contract():
    run = _lint_imports(ROOT)
    assert run.returncode == 0, run.stdout + run.stderr
    assert " 0 broken" in run.stdout


def test_an_import_against_the_layers_breaks_the_contract(tmp_path):
    for package in ("diffeit", "hw"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    mesh = tmp_path / "diffeit" / "mesh" / "_mesh.py"
    mesh.write_text(mesh.read_text() + "\nfrom diffeit import cli  # the sheet's mesh knowing the command line\n")
    run = _lint_imports(tmp_path)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "diffeit's layers: a module imports only from the layers below its own BROKEN" in run.stdout
    assert "diffeit.mesh is not allowed to import diffeit.cli" in run.stdout
    assert "diffeit.mesh._mesh -> diffeit.cli" in run.stdout


CONTRACTS = {
    contract["id"]: contract
    for contract in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
}
HELPERS = {"diffeit._arrays", "diffeit._messages", "diffeit._threads", "diffeit._precision"}


def _modules_of_diffeit() -> set[str]:
    return {
        f"diffeit.{path.stem}"
        for path in (ROOT / "diffeit").iterdir()
        if (path.suffix == ".py" and path.stem != "__init__") or (path / "__init__.py").is_file()
    }


def test_every_module_of_diffeit_has_a_layer():
    """A new module of diffeit is placed in the layers: none escapes the contracts by being left out."""
    layers = CONTRACTS["layers"]["layers"]
    placed = {name.strip().strip("()") for layer in layers for name in re.split(r"[|:]", layer)}
    assert _modules_of_diffeit() - placed == set()


def test_the_leaf_contracts_forbid_all_of_diffeit_but_their_edges():
    """io and hw forbid every module of diffeit, present and future (a wildcard), and allow only
    the edges they name: io onto mesh, protocol and two helpers, hw onto io and protocol."""
    assert CONTRACTS["io-leaf"]["forbidden_modules"] == ["diffeit.*"]
    allowed = {edge.split(" -> ")[1] for edge in CONTRACTS["io-leaf"]["ignore_imports"]}
    assert allowed == {"diffeit.io.**", "diffeit.mesh", "diffeit.protocol", "diffeit._arrays", "diffeit._messages"}
    assert CONTRACTS["hw"]["forbidden_modules"] == ["diffeit.*"]
    assert {edge.split(" -> ")[1] for edge in CONTRACTS["hw"]["ignore_imports"]} == {"diffeit.io", "diffeit.protocol"}


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("diffeit/io/_csv.py", "from ..inverse import OneStep", "diffeit.io stands on the data modules alone"),
        ("hw/frame.py", "from diffeit.mesh import Mesh", "hw uses only diffeit.io and diffeit.protocol"),
        ("diffeit/fit/_background.py", "from ..scene import Scene", "the fits use the memory model, not the simulator"),
    ],
)
def test_a_wildcard_contract_catches_a_wrong_import(tmp_path, module, line, contract):
    for package in ("diffeit", "hw"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    changed = tmp_path / module
    changed.write_text(changed.read_text() + f"\n{line}  # an import the contracts forbid\n")
    run = _lint_imports(tmp_path)
    assert run.returncode == 1, run.stdout + run.stderr
    listing = " ".join(run.stdout.split())
    verdict = re.search(re.escape(contract) + r".*?(KEPT|BROKEN)", listing)
    assert verdict is not None and verdict.group(1) == "BROKEN", run.stdout


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(node: ast.Import | ast.ImportFrom, module: str, path: Path, root: Path) -> list[str]:
    """The dotted names an import statement of `module` (file `path`) imports: modules, and for
    `from M import n`, `M.n` (a module or a name)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if node.level:
        package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
    elif not (path.parent / "__init__.py").exists() and (path.parent / f"{node.module.split('.')[0]}.py").exists():
        base = f"{module.rpartition('.')[0]}.{node.module}"  # a script imports the modules beside it
    else:
        base = node.module
    return [f"{base}.{alias.name}" for alias in node.names]


def _owner(name: str, root: Path) -> str | None:
    """The package a private module or name in dotted `name` belongs to; None when public."""
    parts = name.split(".")
    for i, part in enumerate(parts):
        if part.startswith("_") and not part.startswith("__"):
            owner = parts[:i]
            if (root.joinpath(*owner).with_suffix(".py")).is_file():  # a private name of a module
                owner = owner[:-1]
            return ".".join(owner)
    return None


def private_imports(root: Path, trees: tuple[str, ...] = CHECKED) -> list[str]:
    """Imports under `root`'s `trees` of a private module (or name) of another package."""
    found = []
    for tree in trees:
        for path in sorted((root / tree).rglob("*.py")):
            module = _module_name(path, root)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.Import | ast.ImportFrom):
                    continue
                for name in _imported(node, module, path, root):
                    if name.split(".")[0] not in trees:
                        continue  # the standard library's and third parties' are theirs to police
                    owner = _owner(name, root)
                    if owner is not None and not (module == owner or module.startswith(owner + ".")):
                        found.append(f"{path.relative_to(root)}:{node.lineno} imports {name} (private to {owner})")
    return found


def test_no_module_imports_another_packages_private_modules():
    assert private_imports(ROOT) == []


def test_the_private_module_check_finds_a_private_import(tmp_path):
    (tmp_path / "diffeit" / "mesh").mkdir(parents=True)
    (tmp_path / "diffeit" / "inverse").mkdir()
    for package in ("diffeit", "diffeit/mesh", "diffeit/inverse"):
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "diffeit" / "_arrays.py").write_text("")
    (tmp_path / "diffeit" / "mesh" / "_fields.py").write_text("def _inside(): ...\n")
    (tmp_path / "diffeit" / "mesh" / "_generate.py").write_text("from ._fields import _inside\n")
    (tmp_path / "diffeit" / "inverse" / "priors.py").write_text(
        "from .._arrays import readonly\nfrom ..mesh._fields import distance_to_segments\n"
        "def f():\n    from diffeit.mesh import _fields\n"
    )
    assert private_imports(tmp_path, ("diffeit",)) == [
        "diffeit/inverse/priors.py:2 imports diffeit.mesh._fields.distance_to_segments (private to diffeit.mesh)",
        "diffeit/inverse/priors.py:4 imports diffeit.mesh._fields (private to diffeit.mesh)",
    ]
