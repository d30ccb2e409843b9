"""The service.

The pipeline's stages, supervisor and safe state, status, events, clock.
"""
