"""Controller: the outer loop (feed rate and per-knife piezo offsets), its I/O adapters and the service."""
