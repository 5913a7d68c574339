"""OIBAR benchmarks (issue 10): one module per measured figure, a registry of measurement
functions each returning table rows, and a writer for docs/benchmarks.md.

    python -m oibar_bench [--quick] [--only pose,link] [--out docs/benchmarks.md]

(`make bench` runs it with PYTHONPATH=bench.)
"""

__version__ = "0.1.0"
