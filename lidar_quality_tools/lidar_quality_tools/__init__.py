"""The suite end to end: ``demo`` (``make demo``) and ``process`` (offline batch processing)."""
