"""The shape of the code: modules of one job and bounded size, hydra schemas registered once, outside the models.

The package layers themselves are checked by import-linter (``lint-imports``, contract in pyproject.toml); import
cycles inside the packages and imports deferred into functions here.
"""
import ast
from pathlib import Path

from tools.import_cycles import cycles, project_graph

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("base", "data", "models", "scene", "tasks", "motion")
MAX_LINES = 500  # a module over this is usually several jobs


def modules() -> list[Path]:
    """The product's modules, the entry points and the release tooling (``tools/``)."""
    found = [p for package in PACKAGES for p in sorted((REPO / package).rglob("*.py"))]
    return found + [REPO / "train.py", REPO / "infer.py", *sorted((REPO / "tools").glob("*.py"))]


def test_every_module_is_short_and_says_its_job():
    too_long = [f"{p.relative_to(REPO)}: {n} lines" for p in modules()
                if (n := len(p.read_text().splitlines())) > MAX_LINES]
    assert not too_long, f"over {MAX_LINES} lines: {too_long}"
    silent = [str(p.relative_to(REPO)) for p in modules()
              if p.name != "__main__.py" and not ast.get_docstring(ast.parse(p.read_text()))]
    assert not silent, f"modules without a docstring naming their job: {silent}"


def registrations() -> list[tuple[Path, str, str | None]]:
    """(file, schema name, group) of every ``register_config(...)`` call with literal arguments."""
    found = []
    for path in modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "register_config":
                name = node.args[0].value
                group = next((k.value.value for k in node.keywords if k.arg == "group"), None)
                found.append((path, name, group))
    return found


def test_schema_names_are_unique_and_registered_outside_the_models():
    found = registrations()
    assert len(found) >= 15  # every tool, the train config and its groups
    names = [name for _, name, _ in found]
    twice = sorted(n for n in set(names) if names.count(n) > 1)
    assert not twice, f"schema names used twice: {twice}"
    in_models = [str(p.relative_to(REPO)) for p, _, _ in found if p.relative_to(REPO).parts[0] == "models"
                 and p.name != "cli.py"]
    assert not in_models, f"model modules register hydra schemas: {in_models}"


def test_every_config_names_a_registered_schema():
    names = {name for _, name, _ in registrations()}
    for yaml in sorted((REPO / "configs").rglob("*.yaml")):
        if "hydra" in yaml.parts:
            continue
        text = yaml.read_text()
        schemas = [w.strip(" -,[]") for w in text.split() if w.strip(" -,[]").endswith("_schema")]
        for schema in schemas:
            assert schema in names, f"{yaml.relative_to(REPO)} names {schema}, which nothing registers"


def test_no_import_cycles_inside_the_packages():
    graph = project_graph()
    assert len(graph.modules) > 150
    assert not cycles(graph), f"import cycles: {cycles(graph)}"


def test_project_imports_sit_at_the_top_of_their_module():
    """No import of a project module inside a function, class or conditional block (one place to read what a
    module depends on; a cycle cannot hide behind a deferred import)."""
    deferred = []
    for path in modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)) and node.col_offset > 0:
                names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                relative = isinstance(node, ast.ImportFrom) and node.level > 0
                if relative or any(n.split(".")[0] in PACKAGES for n in names):
                    deferred.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not deferred, f"project imports deferred into a block: {deferred}"
