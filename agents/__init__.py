"""Learning agents: SB3 algorithms built from plain YAML files, and trained agents loaded back as policies
(from arrays: loading a run folder never unpickles, ``magenv.agents.weights``)."""

from magenv.agents.hyperparams import ALGORITHMS, ConfigError, load_hyperparams
from magenv.agents.loading import AgentPolicy, RunError, load_agent

__all__ = ["ALGORITHMS", "AgentPolicy", "ConfigError", "RunError", "load_agent", "load_hyperparams"]
