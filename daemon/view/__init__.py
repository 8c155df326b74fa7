"""``wristscan view``: what a running daemon publishes, logged to a rerun viewer or ``.rrd``
file (:mod:`wristscan.daemon.view.live`; extra ``view``)."""
