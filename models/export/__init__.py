"""ONNX export, int8 quantisation and fp32/int8 benchmarking (training-only; ``dbh export``).

* :func:`export_onnx` / :func:`check_onnx_matches_torch` (``onnx_io``): fp32 export with the
  :class:`~monodbh.models.modeling.registry.ModelSpec` embedded as ONNX metadata.
* :func:`quantize_int8`, :func:`benchmark`, :func:`format_table`, :func:`search_int8`,
  :class:`QuantRecipe`, :data:`DEFAULT_RECIPES`, :func:`recipes_by_name` (``quantize``).
* :func:`export_run` (``cli_impl``): what ``dbh export RUN_DIR [--ship]`` does.
"""
from monodbh.models.export.onnx_io import (SPEC_METADATA_KEY, check_onnx_matches_torch,
                                           export_onnx, make_session, random_feeds, read_spec,
                                           run_session)
from monodbh.models.export.quantize import (DEFAULT_RECIPES, TABLE_COLUMNS, QuantRecipe,
                                            benchmark, format_table, metric_drop, quantize_int8,
                                            recipes_by_name, search_int8)

__all__ = ["SPEC_METADATA_KEY", "check_onnx_matches_torch", "export_onnx", "make_session",
           "random_feeds", "read_spec", "run_session", "DEFAULT_RECIPES", "TABLE_COLUMNS",
           "QuantRecipe", "benchmark", "format_table", "metric_drop", "quantize_int8",
           "recipes_by_name", "search_int8", "export_run"]


def export_run(*args, **kwargs):
    """See :func:`monodbh.models.export.cli_impl.export_run`."""
    from monodbh.models.export.cli_impl import export_run as _f

    return _f(*args, **kwargs)
