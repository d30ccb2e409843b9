"""Benchmarks behind ``planer bench``: one module per part (vision, sim, service), each with ``run(quick)``."""
