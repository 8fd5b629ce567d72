"""Command-line entry points of magenv: ``magenv <command> …`` (see ``magenv.train.cli``)."""
