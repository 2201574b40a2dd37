"""The ``dbh`` command line. Imports ``monodbh.toolkit``/``calib``/``models`` lazily, per command."""
__all__: list[str] = []
