"""The diffusion process, conditioning and samplers (kept apart from the networks)."""
