"""Benchmarks behind ``rlbridge bench``: each measures against a baseline in the same run."""
