"""The documentation site's generated pages (docs/gen_pages.py) are functions of the code: every env's observation
tables, every command's options, every page in the site's navigation."""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path

import pytest
import yaml

from magenv.envs import ENVS
from magenv.train.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("gen_pages", ROOT / "docs" / "gen_pages.py")
gen_pages = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gen_pages)


@pytest.fixture(scope="module")
def pages() -> dict[str, str]:
    return gen_pages.pages()


@pytest.mark.parametrize("env_id", list(ENVS))
def test_env_page_holds_the_feature_tables_and_every_argument(pages, env_id):
    cls = gen_pages.env_class(env_id)
    module = importlib.import_module(cls.__module__)
    page = pages[f"envs/{gen_pages.env_slug(env_id)}.md"]
    tables = [module.FEATURES] + [importlib.import_module(m).EXTRA for m in _memory_modules(module)]
    assert [t for t in tables if t.markdown() not in page] == []
    assert "## Action Space" in page and "## Defaults" in page and "| `scenario` |" in page


def _memory_modules(module) -> list[str]:
    """The modules of an env's extended features (``magenv.envs.ENV_memory``), where it has one."""
    name = module.__name__ + "_memory"
    return [name] if importlib.util.find_spec(name) else []


@pytest.mark.parametrize("name", list(COMMANDS))
def test_command_page_lists_every_option_of_its_parser(pages, name):
    page = pages[f"commands/{name}.md"]
    flags = [s for a in gen_pages.command_parser(name)._actions for s in a.option_strings if s not in ("-h", "--help")]
    assert [f for f in flags if f"`{f}`" not in page] == [], name
    assert page.startswith(f"# `magenv {name}`")


def test_navigation_holds_every_page_and_the_home_page_links_into_the_site(pages):
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())

    def leaves(nav):
        for entry in nav:
            value = next(iter(entry.values())) if isinstance(entry, dict) else entry
            yield from leaves(value) if isinstance(value, list) else [value]

    in_nav = set(leaves(gen_pages._expand(config["nav"])))
    written = {p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")}
    assert (set(pages) | written) - in_nav == set() and in_nav - set(pages) - written == set()
    assert "](docs/" not in pages["index.md"] and "](results.md)" in pages["index.md"]
