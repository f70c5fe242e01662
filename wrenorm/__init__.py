"""wrenorm: renormalised robot simulation.

Keep the coarse model, fit effective resolution-dependent parameters that reproduce the real
behaviour that matters. See README.md.
"""
__version__ = "0.1.0"
