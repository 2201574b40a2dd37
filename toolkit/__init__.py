"""The measuring pipeline: rope detection, scale, unprojection, DBH fitting, point-cloud output.

Imported by ``monodbh.cli``; imports ``monodbh.calib`` and the runtime predictors of
``monodbh.models`` only (never training code or the scene generator).
"""
# light imports only (numpy, cv2): no torch here
from .rope import RopeCandidate, RopeDetection, detect_rope  # noqa: E402

__all__: list[str] = ["RopeCandidate", "RopeDetection", "detect_rope"]
