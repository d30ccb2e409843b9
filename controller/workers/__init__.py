"""Measurement in worker processes.

The pool, the service's end of a worker, the worker process.
"""
