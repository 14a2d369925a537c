"""Test helpers for the exports: the ONNX runtime (or a skip) and an exported NumPy module loaded."""
import importlib.util

import pytest


def onnx_runtime():
    """The onnxruntime module; the test skips where the onnx extra is not installed."""
    why = "needs the onnx extra (pip install '.[onnx]')"
    pytest.importorskip("onnx", reason=why)
    return pytest.importorskip("onnxruntime", reason=why)


def load_module(path):
    spec = importlib.util.spec_from_file_location("exported", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
