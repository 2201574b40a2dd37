"""Networks: runtime ONNX predictors and shipped models (here), plus training-only subpackages.

``monodbh.models.runtime`` (onnxruntime only) is imported by ``monodbh.toolkit``. The
subpackages ``synthetic`` (scene generator), ``modeling`` (torch nn.Modules), ``training`` and
``export`` are training-only: the measuring path never imports them.
"""
__all__: list[str] = []
