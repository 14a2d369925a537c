"""Export: a model on one graph as a file that runs without mpnode.

Owns: `arrays` (the model on a graph as plain settings and arrays), `standalone` (the
exported module's docstring, decoding and rollout around the NumPy path's field and RK4, all
copied into it), `numpy_module` (writes OUT.py)
and `onnx_model` (writes OUT.onnx; needs the onnx extra, imported only there).  May
import: model, data, engine, base.
"""
from .numpy_module import numpy_module_source, write_numpy_module  # noqa: F401
