"""km.poisson (in progress)."""
