"""HeartUnloadNet: graphs from the store, splits, the model and its ablations/baselines, the plain
training loop and its Ray Train wrapper, metrics, evaluation, benchmarks and network unloading."""
