"""Done cases of a store as the network's graphs: the cases read, their features and normalisation,
the splits, the batches (labelled and unlabelled mixed, augmented, built from a graph table)."""
