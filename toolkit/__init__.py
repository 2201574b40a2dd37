"""The measuring pipeline: rope detection, scale, unprojection, DBH fitting, point-cloud output.

Imported by ``monodbh.cli``; imports ``monodbh.calib`` and the runtime predictors of
``monodbh.models`` only (never training code or the scene generator).
"""
__all__: list[str] = []
