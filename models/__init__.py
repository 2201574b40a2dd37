"""Networks: the shipped models (``*.onnx`` + ``manifest.json``, here), their runtime, and training-only subpackages.

``monodbh.models.runtime`` (onnxruntime only, one module per network) is imported by
``monodbh.toolkit``. The subpackages ``synthetic`` (scene generator), ``modeling`` (torch
nn.Modules), ``training`` and ``export`` are training-only: the measuring path never imports them.
"""
__all__: list[str] = []
