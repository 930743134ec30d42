"""Benchmark families: one folder each behind the interfaces of ``base``, registered in ``registry``."""
