"""The ``wristscan`` command line: ``app`` holds the typer app, each other module is one verb
(``wristscan calibrate sensor`` is ``cli/calibrate.py``). Modules whose name starts with ``_``
are not verbs: ``_common`` holds what verbs share (exit codes, ``fail``, config loading, motion
confirmation, progress output, shared options), ``_remote`` how ``status`` and ``record`` reach
a running daemon, ``_calibrate_table`` the ``calibrate table`` and ``calibrate latency``
commands."""
