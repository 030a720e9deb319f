"""The install puts nothing but the project's namespace into site-packages."""

from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _declared():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return cfg["packages"], cfg.get("package-dir", {})


def test_every_package_folder_is_declared_under_the_namespace():
    packages, mapping = _declared()
    assert all(p == "uwb_env" or p.startswith("uwb_env.") for p in packages)
    found = set()
    for init in ROOT.glob("uwb_env/**/__init__.py"):
        found.add(".".join(init.parent.relative_to(ROOT).parts))
    for name, folder in mapping.items():  # repository folders installed inside the namespace
        for init in (ROOT / folder).glob("**/__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((name, *rel)))
    assert found == set(packages)


def test_repository_folders_import_inside_the_namespace():
    import uwb_env.agents.registry
    import uwb_env.training.evaluate

    assert Path(uwb_env.agents.registry.__file__).parent == ROOT / "agents"
    assert Path(uwb_env.training.evaluate.__file__).parent == ROOT / "training"
