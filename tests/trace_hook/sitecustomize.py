"""Starts the dependency tracer (tests/deps_trace.py) in every Python process of a traced pipeline run: put this
folder and tests/ on PYTHONPATH and set ADAPTDIFFUSER_TRACE_DEPS; only DVC's stage processes ($DVC_STAGE) trace."""

import os

if os.environ.get("ADAPTDIFFUSER_TRACE_DEPS") and os.environ.get("DVC_STAGE"):
    import deps_trace

    deps_trace.install_from_env()
