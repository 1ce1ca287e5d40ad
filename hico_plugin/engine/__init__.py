"""Training engine: trainer, optimisers, checkpoints, callbacks; knows nothing about Gaussians."""
