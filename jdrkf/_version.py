"""The version of jdrkf, read by the build backend (pyproject.toml: `[tool.hatch.version]`)."""

__version__ = "0.1.0"
