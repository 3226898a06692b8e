"""HeartUnloadNet and its parts (the sparse GAT layer, the weight average), the PCA baseline, and a
mesh prepared once for repeated single-case inference."""
