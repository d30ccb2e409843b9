"""Benchmarks behind ``planer bench``: one module per part (vision, sim, service).

Each module exposes ``run(quick)``.
"""
