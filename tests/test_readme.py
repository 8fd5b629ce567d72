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


README = (ROOT / "README.md").read_text()


def _table(text: str, header: str) -> list[list[str]]:
    """The rows (cells) of the Markdown table whose header line starts with ``header``."""
    lines = text[text.index(header) :].splitlines()
    rows = []
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def test_readme_is_short():
    assert len(README.splitlines()) <= 150


def test_readme_env_table_is_the_registered_envs_with_their_default_scenarios():
    import inspect

    from magenv.envs import ENVS

    rows = _table(README, "| id | the policy chooses |")
    assert [r[0].strip("`") for r in rows] == list(ENVS)
    for env_id, *_, scenario in rows:
        module, name = ENVS[env_id.strip("`")][0].split(":")
        cls = getattr(__import__(module, fromlist=[name]), name)
        assert scenario.strip("`") == inspect.signature(cls.__init__).parameters["scenario"].default


def test_readme_results_table_is_the_benchmark_summary_of_every_shipped_agents_card():
    """Every figure of the README's results table is ``magenv benchmark`` output: the summary of the shipped
    agents' score cards, each a protocol run (the suite's seeds, full trials) of every task of its env."""
    from magenv.agents.loading import pretrained_agents
    from magenv.benchmark import suite
    from magenv.train.benchmark import read_card, summary_lines

    paths = sorted((ROOT / "docs" / "benchmark" / "shipped").glob("*.json"))
    cards = [read_card(p) for p in paths]
    assert sorted(c["agent"] for c in cards) == sorted(f"pretrained:{a}" for a in pretrained_agents())
    for card in cards:
        env = card["agent"].split("/")[-1]
        assert card["protocol"] and card["suite"] == suite.VERSION and card["skipped"] == []
        tasks = [t for t in suite.TASKS if t.env_id.endswith(env)]
        assert [(t["task"], t["rule"]) for t in card["tasks"]] == [(t.name, t.rule) for t in tasks]
    header = "| task | rule (score 0) |"
    for page in (README, (ROOT / "docs" / "benchmark" / "shipped.md").read_text()):
        assert page[page.index(header) :].split("\n\n", 1)[0].splitlines() == summary_lines(cards)


def test_commands_and_scripts_that_the_docs_name_exist():
    """Every `python -m studies.X`, `benchmarks/X.py`, `magenv COMMAND` and `make TARGET` in the README, the docs
    pages and the shipped agents' cards names a real script, command or target."""
    from magenv.train.cli import COMMANDS

    texts = [p.read_text() for p in [*PAGES, *ROOT.glob("agents/pretrained/*/card.md")]]
    text = "\n".join(texts)
    studies = set(re.findall(r"python -m studies\.([a-z_]+)", text))
    assert [s for s in studies if not (ROOT / "studies" / f"{s}.py").is_file()] == []
    scripts = set(re.findall(r"\b(benchmarks|studies)/(\w+)\.py", text))
    assert [f"{d}/{s}.py" for d, s in scripts if not (ROOT / d / f"{s}.py").is_file()] == []
    commands = set(re.findall(r"`magenv ([a-z]+)", text))
    assert commands - set(COMMANDS) == set()
    targets = set(re.findall(r"`make ([\w-]+)`", text))
    makefile = (ROOT / "Makefile").read_text()
    assert [t for t in targets if not re.search(rf"^{re.escape(t)}:", makefile, flags=re.M)] == []
