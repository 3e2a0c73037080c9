"""Training and evaluation of the meta models (offline; the nodes never import this)."""
