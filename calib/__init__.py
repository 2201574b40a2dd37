"""Camera calibration: camera model, cam.yaml I/O, checkerboard calibration, pose, photo loading.

Lives here: everything about the camera. May be imported by ``monodbh.toolkit`` and
``monodbh.cli``; imports nothing else from monodbh.
"""
__all__: list[str] = []
