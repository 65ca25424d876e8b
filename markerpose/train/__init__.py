"""Training: random scenes from the renderer, augmentations, and the training loops."""
