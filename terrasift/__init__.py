"""terrasift: LAS/LAZ tiles in, terrain knowledge out."""

__version__ = "0.1.0"
