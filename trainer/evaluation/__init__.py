"""A trained run scored and used: predictions (single networks, ensembles, test-time rotations),
the paper's metrics, evaluation against the store's labels and a converged reference."""
