"""The service: the pipeline's stages, supervisor and safe state, status, events, clock."""
