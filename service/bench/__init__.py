"""Benchmarks: the paper's experiment and performance measurements. Presentation lives here, not in
the library modules."""
