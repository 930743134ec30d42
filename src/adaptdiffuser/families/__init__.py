"""Benchmark families: one folder each behind the interfaces of :mod:`adaptdiffuser.contract`, registered in
:mod:`adaptdiffuser.family_registry`."""
