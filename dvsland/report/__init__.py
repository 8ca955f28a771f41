"""Run output: results.json / traces.npz, TensorBoard, figures, the summary table.

Public names: :func:`write_json` (strict JSON, NaN -> null: every JSON file), :func:`write_results_json`, :func:`read_results_json`, :func:`write_traces_npz`,
:func:`format_table`, :class:`TensorBoardLogger`, :func:`write_figures`, :func:`descent_figure`,
:func:`lowest_altitude_chart`.
"""

from .results import read_results_json, to_json, write_json, write_results_json, write_traces_npz
from .table import format_table

__all__ = ["write_json", "to_json", "write_results_json", "read_results_json", "write_traces_npz", "format_table",
           "TensorBoardLogger", "write_figures", "descent_figure", "lowest_altitude_chart"]


def __getattr__(name):  # lazy: matplotlib and tensorboard load only when used
    if name == "TensorBoardLogger":
        from .tensorboard import TensorBoardLogger

        return TensorBoardLogger
    if name in ("write_figures", "descent_figure", "lowest_altitude_chart"):
        from . import figures

        return getattr(figures, name)
    raise AttributeError(name)
