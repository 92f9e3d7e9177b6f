"""biotac-twin: the testbed twin (CLI entry point `twin`)."""

__version__ = "0.1.0"
