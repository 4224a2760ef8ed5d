"""The house rules the linters cannot state: no private name crosses a module boundary, and every
package folder is installed under the import name its folder maps to."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
PACKAGE_DIR: dict[str, str] = SETUPTOOLS["package-dir"]


def _modules() -> dict[str, Path]:
    """Every module of the package by import name, found through ``package-dir`` (generated code aside)."""
    modules: dict[str, Path] = {}
    for package, folder in PACKAGE_DIR.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            if "__pycache__" in path.parts or path.name.endswith("_pb2.py"):
                continue
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            # The longest mapping wins: services/reconstruct/... is lelsonar.reconstruct..., never lelsonar....
            modules.setdefault(".".join([package, *parts]), path)
    return modules


def _imported_from(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ``from … import`` statement of ``module`` reads."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    if path.name != "__init__.py":
        base.pop()
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def test_the_module_walk_finds_the_package():
    modules = _modules()
    # One module per layer at least, so an empty walk cannot pass the tests below.
    for name in ("lelsonar.codec", "lelsonar.signal.energy", "lelsonar.reconstruct.estimate.lel", "lelsonar.cli.main"):
        assert name in modules, f"{name} not found under {PACKAGE_DIR}"


def test_no_private_name_is_imported_from_another_lelsonar_module():
    crossings = []
    for module, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            source = _imported_from(module, path, node)
            if source != "lelsonar" and not source.startswith("lelsonar."):
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    crossings.append(f"{path.relative_to(ROOT)}:{node.lineno}: {alias.name} from {source}")
    assert not crossings, "private names imported across modules (make them public or move them):\n" + "\n".join(
        crossings
    )


def test_every_package_folder_is_installed_under_its_import_name():
    packages = set(SETUPTOOLS["packages"])
    folder_of = {name: ROOT / folder for name, folder in PACKAGE_DIR.items()}
    missing = []
    for top in ("services", "schemas"):
        for init in sorted((ROOT / top).rglob("__init__.py")):
            folder = init.parent
            if "__pycache__" in folder.parts:
                continue
            # Its import name under the rule: the deepest package-dir entry that holds the folder.
            owners = [(name, root) for name, root in folder_of.items() if folder == root or root in folder.parents]
            if not owners:
                missing.append(f"{folder.relative_to(ROOT)}: under no package-dir entry")
                continue
            name, root = max(owners, key=lambda o: len(o[1].parts))
            import_name = ".".join([name, *folder.relative_to(root).parts])
            if import_name not in packages:
                missing.append(f"{folder.relative_to(ROOT)}: {import_name} is not in [tool.setuptools] packages")
    assert not missing, "\n".join(missing)
    # And no listed package lacks its folder.
    for name in packages:
        owners = [(p, folder_of[p]) for p in folder_of if name == p or name.startswith(p + ".")]
        assert owners, f"{name} is in packages but under no package-dir entry"
        package, root = max(owners, key=lambda o: len(o[0]))
        folder = root.joinpath(*name.split(".")[len(package.split(".")) :])
        assert (folder / "__init__.py").is_file(), f"{name} is in packages, but {folder} has no __init__.py"
