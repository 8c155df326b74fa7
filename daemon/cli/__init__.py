"""The ``wristscan`` command line: ``app`` holds the typer app, each other module is one verb
(``wristscan calibrate sensor`` is ``cli/calibrate.py``); ``_common`` holds what verbs share."""
