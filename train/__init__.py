"""Command-line entry points of magenv: ``magenv <command> …`` (see ``train.cli``)."""
