"""Environments the planner runs in; each plugs in through :class:`adaptdiffuser.envs.base.PlanningEnv`."""
