"""AdaptDiffuser: a diffusion planner that evolves itself with synthetic, discriminated data."""

__version__ = "0.1.0"
