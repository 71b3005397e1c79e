"""The documentation site (mkdocs.yml, docs/): it builds with --strict (no broken link or missing
reference), every public module has an API page, the tutorials' code runs as written, the
command lines the pages show exist, the benchmarks write the tables the pages include, and the
README stays a short front page."""

import contextlib
import io
import os
import pkgutil
import re
import shlex
import subprocess
import sys
import warnings
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
API = DOCS / "api"
# The pages whose ```python blocks run, top to bottom in one namespace, as a reader would run them
# (from the repository's root: tests/data/ is where they find the recordings). A block whose
# first line is a snippet include (--8<--) is code from a file the tests run on their own.
TUTORIALS = [
    "README.md",
    "docs/getting-started.md",
    pytest.param("docs/tutorials/imaging.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/real-recordings.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/calibration.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/fitting.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/scenes.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/hardware.md", marks=pytest.mark.slow),
    pytest.param("docs/tutorials/curved-skins.md", marks=pytest.mark.slow),
]
# Public modules documented elsewhere than the API reference: the demo (Getting started) and the
# command line (every command's --help, and the tutorials).
NOT_IN_API = {"diffeit.demo", "diffeit.cli"}


def _fences(text: str) -> list[tuple[str, str]]:
    """(info string, body) of every fenced code block of a Markdown text."""
    blocks, info, body = [], None, []
    for line in text.splitlines():
        stripped = line.strip()
        if info is None and stripped.startswith("```"):
            info, body = stripped[3:].strip(), []
        elif info is not None and stripped.startswith("```"):
            blocks.append((info, "\n".join(body) + "\n"))
            info = None
        elif info is not None:
            body.append(line)
    return blocks


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


# -- the site --------------------------------------------------------------------------------------


def test_the_site_builds_strictly(tmp_path):
    """`mkdocs build --strict`: a broken link, a missing anchor, an unresolved API reference, a
    missing snippet or a docstring the handler cannot parse fails the build."""
    environment = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # Material's banner about MkDocs 2
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")]
    run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env=environment, timeout=600)
    assert run.returncode == 0, f"mkdocs build --strict failed (is the docs extra installed?):\n{run.stderr}"
    assert "WARNING" not in run.stderr, run.stderr
    site = tmp_path / "site"
    for page in ("index.html", "api/fit.html", "benchmarks.html", "experiments/index.html"):
        assert (site / page).is_file(), page
    # The generated reference holds the docstrings, the benchmark page the tables of docs/benchmarks/.
    assert "memory_uncertainty" in (site / "api" / "fit.html").read_text()
    benchmarks = (site / "benchmarks.html").read_text()
    assert "<table>" in benchmarks and "| triangles |" not in benchmarks and "--8&lt;--" not in benchmarks
    assert (site / "experiments" / "results" / "sweep" / "sweep.png").is_file()  # docs/hooks/outside_files.py


def _public_modules() -> set[str]:
    """diffeit, hw and every module under them whose dotted path has no part starting with _."""
    import diffeit
    import hw

    names = {"diffeit", "hw"}
    for package in (diffeit, hw):
        for module in pkgutil.walk_packages(package.__path__, prefix=package.__name__ + "."):
            if not any(part.startswith("_") for part in module.name.split(".")):
                names.add(module.name)
    return {name for name in names if not any(name == skip or name.startswith(skip + ".") for skip in NOT_IN_API)}


def test_every_public_module_has_an_api_page_in_the_navigation():
    documented = {}
    for page in API.glob("*.md"):
        for name in re.findall(r"^::: ([\w.]+)", page.read_text(), flags=re.MULTILINE):
            documented[name] = page
    missing = sorted(_public_modules() - set(documented))
    assert not missing, f"public modules without an API page (add `::: NAME` to a page of docs/api/): {missing}"
    navigation = (ROOT / "mkdocs.yml").read_text()
    for page in {*documented.values(), API / "index.md"}:
        assert f"api/{page.name}" in navigation, f"docs/api/{page.name} is not in mkdocs.yml's nav"
    index = (API / "index.md").read_text()
    for page in API.glob("*.md"):
        assert page.name == "index.md" or f"({page.name})" in index, f"docs/api/index.md does not link {page.name}"


# -- the tutorials' code ---------------------------------------------------------------------------


def _python_blocks(page: Path) -> list[str]:
    return [
        body
        for info, body in _fences(page.read_text())
        if info.split()[:1] == ["python"] and not body.lstrip().startswith("--8<--")
    ]


@pytest.mark.parametrize("page", TUTORIALS)
def test_the_tutorials_code_runs(page, tmp_path, monkeypatch):
    blocks = _python_blocks(ROOT / page)
    assert blocks, f"{page} has no python blocks"
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    (tmp_path / "diffeit").symlink_to(ROOT / "diffeit")  # diffeit/scene/examples/*.toml
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__tutorial__"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the calibration's warnings are what some pages show
        for number, block in enumerate(blocks, 1):
            try:
                exec(compile(block, f"{page}, python block {number}", "exec"), namespace)
            except Exception as error:
                raise AssertionError(f"{page}, python block {number} failed: {error!r}\n{block}") from error


# -- the command lines the pages show --------------------------------------------------------------


def _command_lines() -> list[tuple[Path, list[str]]]:
    """Every command of a ```sh block of the README and the docs, split into words (comments
    and the continuation of wrapped lines handled)."""
    lines = []
    for path in _markdown_files():
        for info, body in _fences(path.read_text()):
            if info.split()[:1] not in (["sh"], ["bash"], ["console"]):
                continue
            for line in body.replace("\\\n", " ").splitlines():
                words = shlex.split(line, comments=True)
                if words:
                    lines.append((path, words))
    return lines


def _help(command: str) -> str:
    from diffeit.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main([command, "--help"])
    return out.getvalue()


def test_the_command_lines_the_pages_show_exist():
    makefile = (ROOT / "Makefile").read_text()
    helps: dict[str, str] = {}
    seen = set()
    for path, words in _command_lines():
        where = f"{path.relative_to(ROOT)}: {shlex.join(words)}"
        program = words[0].removeprefix(".venv/bin/")
        if program == "diffeit":
            command = words[1]
            if command not in helps:
                helps[command] = _help(command)
            options = [word.split("=")[0] for word in words[2:] if word.startswith("-")]
            unknown = [
                option for option in options if not re.search(rf"(^|[\s,\[]){re.escape(option)}\b", helps[command])
            ]
            assert not unknown, f"{where}: diffeit {command} has no option {unknown}"
            seen.add(command)
        elif program == "make":
            for target in words[1:]:
                if "=" not in target:
                    assert re.search(rf"^{re.escape(target)}:", makefile, flags=re.MULTILINE), f"{where}: no target"
        elif program in ("python", "python3") and words[1].endswith(".py"):
            script = ROOT / words[1]
            assert script.is_file(), f"{where}: no such script"
            source = script.read_text()
            unknown = [word for word in words[2:] if word.startswith("--") and f'"{word.split("=")[0]}"' not in source]
            assert not unknown, f"{where}: {words[1]} has no option {unknown}"
    assert {"demo", "simulate", "reconstruct", "fit", "acquire", "live", "emulate"} <= seen


# -- the benchmarks' tables ------------------------------------------------------------------------


def test_every_benchmark_writes_the_table_file_its_page_includes():
    page = (DOCS / "benchmarks.md").read_text()
    for script in sorted((ROOT / "benchmarks").glob("[!_]*.py")):
        assert "write_tables(" in script.read_text(), f"{script.name} does not write its tables"
        table = f"docs/benchmarks/{script.stem}.md"
        assert (ROOT / table).is_file(), f"{table} is missing: run `make bench` or write a placeholder"
        assert f'--8<-- "{table}"' in page, f"docs/benchmarks.md does not include {table}"
    # Tables are written by the scripts, never pasted: no page but the included files has one.
    for path in _markdown_files():
        if path.parent != DOCS / "benchmarks":
            assert "| --- | --- |" not in path.read_text(), f"{path.relative_to(ROOT)} holds a pasted benchmark table"


def test_the_table_file_a_benchmark_writes(tmp_path, monkeypatch, capsys):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import _common
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    monkeypatch.setattr(_common, "TABLES", tmp_path)
    printed = _common.record_output()
    try:
        print("machine: a test, 2 CPUs")
        print()
        table = _common.MarkdownTable(["triangles", "time"])
        table.row(["722", "1.8 ms"])
        print("note: one\nnote: two")
    finally:
        path = _common.write_tables("example", printed, date="2026-01-01")
    print("after")  # the copy has stopped
    text = path.read_text()
    assert path == tmp_path / "example.md" and "after" not in text
    assert "Run of 2026-01-01: `python " in text
    assert (
        "machine: a test, 2 CPUs\n\n| triangles | time |\n| --- | --- |\n| 722 | 1.8 ms |\n\nnote: one\n\nnote: two\n"
        in text
    )
    assert "machine: a test" in capsys.readouterr().out  # the terminal still sees everything


# -- the README ------------------------------------------------------------------------------------


def test_the_readme_is_a_short_front_page_whose_links_exist():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) < 150
    assert "make demo" in readme and "make test" in readme
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme)
    local = [target for target in targets if not re.match(r"[a-z]+://", target)]
    assert any(target.endswith(".png") for target in local), "the README shows no picture"
    for target in local:
        assert (ROOT / target).exists(), f"README links {target}, which does not exist"
