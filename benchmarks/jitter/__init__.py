"""HRT loop jitter per coupling pattern (thesis 5.3) and the GIL study (docs/jitter.md, gil.md).

Run ``python -m benchmarks.jitter run --help``; :mod:`benchmarks.jitter.cli` lists the modules.
"""
