"""mergesvc: multi-robot object-map merging by semantic, uncertainty-aware graph matching."""
__version__ = "0.1.0"
