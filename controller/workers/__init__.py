"""Measurement in worker processes: the pool, the service's end of a worker, the worker process."""
