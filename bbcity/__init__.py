"""bbcity: the composition root (CLI, pipeline orchestration, benchmarks).

The stage packages (data_synth, recon, billboards, render) never import this one.
"""

__version__ = "0.1.0"
