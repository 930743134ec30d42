"""Trajectory data: the Parquet schema, expert collection and training windows."""
