"""Export: a model on one graph as a file that runs without mpnode.

Owns: `arrays` (the model on a graph as plain settings and arrays), `standalone` (the
rollout in NumPy alone, copied into the exported module), `numpy_module` (writes OUT.py)
and `onnx_model` (writes OUT.onnx; needs the onnx extra, imported only there).  May
import: model, data, engine, base.
"""
from .numpy_module import numpy_module_source, write_numpy_module  # noqa: F401
