"""The trainer's errors. Each message is one line; the CLI reports it with exit status 2."""


class TrainerError(ValueError):
    """Bad input to training / evaluation / network unloading; the message is one line."""


class TrainingDiverged(TrainerError):
    """The training loss (or validation loss) turned non-finite: every rank stops at the same epoch."""
