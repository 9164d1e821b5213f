"""km.sparse (in progress)."""
