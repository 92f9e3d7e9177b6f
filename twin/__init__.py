"""biotac-twin: the testbed twin (CLI entry point `twin`)."""

__version__ = "0.1.0"

from twin.envs import register_envs  # noqa: E402

register_envs()
