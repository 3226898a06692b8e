"""The command line's side of the commands: what a user reads in the terminal (one-line errors and
warnings, progress, tables, JSON lines) and how a command runs there (threads, signals, the memory a
solve needs). With cli.py it is the only code that names command-line flags."""
