"""ControlNet-style tactile adapters mapping frozen touch embeddings to the privileged latent."""
