"""The generated pages of the documentation site: ``mkdocs build`` runs this file as a hook (``mkdocs.yml``).

* ``index.md`` — the README, its ``docs/`` links made relative to the site;
* ``envs/index.md`` and ``envs/ENV.md`` — one page per env of ``magenv.envs.ENVS``: its class docstring (the
  observation tables are the env's ``FeatureTable``s, put there by ``magenv.envs.features.document``) and its
  arguments with their defaults, read from the signature;
* ``commands/index.md`` and ``commands/NAME.md`` — one page per ``magenv`` command of ``magenv.train.cli.COMMANDS``:
  its module docstring, usage and every option with its default and help, read from the argument parser.

Each page is a function of the code, so the site cannot drift from it; ``tests/test_docs.py`` checks the pages.
The hook adds them to the site's files and to its navigation, after ``envs/index.md`` and ``commands/index.md``:
a new env or command needs no line here or in ``mkdocs.yml``.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def env_class(env_id: str) -> type:
    from magenv.envs import ENVS

    module, name = ENVS[env_id][0].split(":")
    return getattr(importlib.import_module(module), name)


def env_slug(env_id: str) -> str:
    return env_id.split("/")[-1]


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def env_page(env_id: str) -> str:
    """An env's page: its class docstring and its arguments (name, default) from the signature."""
    cls = env_class(env_id)
    doc = inspect.cleandoc(cls.__doc__ or "")
    args = ["| argument | default |", "|---|---|"]
    for p in list(inspect.signature(cls.__init__).parameters.values())[1:]:
        default = "required" if p.default is inspect.Parameter.empty else f"`{p.default!r}`"
        args.append(f"| `{p.name}` | {_cell(default)} |")
    head = f'# `{env_id}`\n\n`{cls.__module__}.{cls.__name__}`; `gymnasium.make("{env_id}", **arguments)`.\n\n'
    return head + doc + "\n\n## Defaults\n\n" + "\n".join(args) + "\n"


def envs_index() -> str:
    from magenv.envs import ENVS

    rows = ["| id | class | default scenario |", "|---|---|---|"]
    for env_id in ENVS:
        cls = env_class(env_id)
        scenario = inspect.signature(cls.__init__).parameters["scenario"].default
        rows.append(f"| [`{env_id}`]({env_slug(env_id)}.md) | `{cls.__module__}.{cls.__name__}` | `{scenario}` |")
    intro = (
        "# Environments\n\nEach page is the env's class docstring (description, action, observation tables with "
        "units and ranges, reward, `info`) and its arguments; the conventions all five share are in "
        "[Conventions and training](../environments.md).\n\n"
    )
    return intro + "\n".join(rows) + "\n"


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser of ``magenv NAME``, built as ``magenv.train.cli.main`` builds it."""
    from magenv.train.cli import COMMANDS

    module, description = COMMANDS[name]
    p = argparse.ArgumentParser(prog=f"magenv {name}", description=description)
    importlib.import_module(module).add_arguments(p)
    return p


def command_page(name: str) -> str:
    """A command's page: what it does, its module docstring, usage and every option (default, help)."""
    from magenv.train.cli import COMMANDS

    module, description = COMMANDS[name]
    p = command_parser(name)
    rows = ["| option | default | what it does |", "|---|---|---|"]
    for action in p._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        flags = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.dest}` (positional)"
        default = "–" if action.default in (None, argparse.SUPPRESS) or action.required else f"`{action.default!r}`"
        help_text = (action.help or "") % {"default": action.default} if action.help else ""
        rows.append(f"| {flags} | {_cell(default)} | {_cell(help_text)} |")
    doc = inspect.cleandoc(importlib.import_module(module).__doc__ or "")
    usage = p.format_usage().strip().removeprefix("usage: ")
    return (
        f"# `magenv {name}`\n\n{description[0].upper()}{description[1:]}.\n\n```\n{usage}\n```\n\n"
        f"{doc}\n\n## Options\n\n" + "\n".join(rows) + "\n"
    )


def commands_index() -> str:
    from magenv.train.cli import COMMANDS

    rows = ["| command | what it does |", "|---|---|"]
    rows += [f"| [`magenv {name}`]({name}.md) | {help_text} |" for name, (_, help_text) in COMMANDS.items()]
    intro = (
        "# Commands\n\nOne page per `magenv` command, generated from its argument parser. Exit statuses, "
        "training configs and run folders: [Training and run folders](../cli.md).\n\n"
    )
    return intro + "\n".join(rows) + "\n"


def home_page() -> str:
    """The README as the site's home page: links into ``docs/`` made relative to the site."""
    return re.sub(r"\]\(docs/", "](", (ROOT / "README.md").read_text())


def pages() -> dict[str, str]:
    """Every generated page: path in the site → Markdown."""
    from magenv.envs import ENVS
    from magenv.train.cli import COMMANDS

    out = {"index.md": home_page(), "envs/index.md": envs_index(), "commands/index.md": commands_index()}
    out.update({f"envs/{env_slug(e)}.md": env_page(e) for e in ENVS})
    out.update({f"commands/{name}.md": command_page(name) for name in COMMANDS})
    return out


def _expand(nav: list) -> list:
    """The navigation with each generated section's pages after its index page."""
    from magenv.envs import ENVS
    from magenv.train.cli import COMMANDS

    after = {
        "envs/index.md": [{env_slug(e): f"envs/{env_slug(e)}.md"} for e in ENVS],
        "commands/index.md": [{f"magenv {n}": f"commands/{n}.md"} for n in COMMANDS],
    }
    out: list = []
    for entry in nav:
        if isinstance(entry, dict):
            out.append({k: _expand(v) if isinstance(v, list) else v for k, v in entry.items()})
        else:
            out.append(entry)
        out.extend(after.get(entry, []) if isinstance(entry, str) else [])
    return out


def on_config(config):
    """MkDocs hook: the generated pages in the navigation."""
    config["nav"] = _expand(config["nav"])
    return config


def on_files(files, config):
    """MkDocs hook: the generated pages among the site's files."""
    from mkdocs.structure.files import File

    for path, text in pages().items():
        files.append(File.generated(config, path, content=text))
    return files
