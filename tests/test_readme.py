"""The Python snippets of the README and of the docs/ pages it links run as written."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SNIPPETS = [(page, code) for page in PAGES for code in re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)]


def test_readme_and_docs_have_snippets():
    assert sum(page.name == "README.md" for page, _ in SNIPPETS) >= 1 and len(SNIPPETS) >= 2


def test_readme_links_every_docs_page():
    readme = (ROOT / "README.md").read_text()
    assert [p.name for p in PAGES[1:] if f"(docs/{p.name})" not in readme] == []


@pytest.mark.parametrize(
    "page, code", SNIPPETS, ids=[f"{page.stem}-snippet{i}" for i, (page, _) in enumerate(SNIPPETS)]
)
def test_snippet_runs(page, code):
    exec(compile(code, str(page), "exec"), {"__name__": "readme"})


def test_cli_page_lists_every_dagger_config_key():
    from magenv.agents.dagger import DEFAULTS

    text = (ROOT / "docs" / "cli.md").read_text()
    section = text[text.index("### Teacher–student training (DAgger)") :].split("\n### ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `")]
    assert [key for key in DEFAULTS if not any(f"`{key}`" in row.split(" | ")[0] for row in rows)] == []
