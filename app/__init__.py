"""What each `heartctl` command does, below its command-line parsing: functions that take checked
values and return typed results, which cli.py prints."""
