"""Controller: the outer loop (feed, per-knife piezo offsets), bus adapters, the service."""
