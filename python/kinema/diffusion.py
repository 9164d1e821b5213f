"""km.diffusion (in progress)."""
