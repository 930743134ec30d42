"""AdaptDiffuser: a diffusion planner that evolves itself with synthetic, discriminated data.

Importing the package registers the benchmark families with config (:mod:`adaptdiffuser.family_registry`), so
params can be read from any module of it."""

from adaptdiffuser import family_registry  # noqa: F401  (registers each family's settings model with config)

__version__ = "0.1.0"
