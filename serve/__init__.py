"""HTTP serving of an exported occflownet ONNX model (FastAPI + onnxruntime; never imports torch)."""
