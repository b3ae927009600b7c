"""Starting and stopping the portal's processes, in one place.

- `stack.run`: the whole stack as `make run` runs it (`python -m stack run`);
- `stack.processes`: child processes with their logs, the command lines of gunicorn, Celery
  and `manage.py`, probes that a service answers, a Redis of our own;
- `stack.anvil`: an anvil node (the worker tests and the benchmarks start their own).

Nothing here imports the portal's Django apps: Django steps run as `manage.py` subprocesses.
"""
