"""ONNX export of the occflownet inference graph (torch → ONNX, parity-checked against onnxruntime)."""
