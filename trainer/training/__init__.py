"""Training: the plain PyTorch loop, Ray Train around it, where and how a run is placed, the
learning-rate schedule, checkpoints, fine-tuning from a parent run, and the allocator's settings."""
