"""Controller: the outer loop (feed rate, per-knife piezo offsets), its bus adapters, the service."""
