"""embedrl export: trained policy -> ONNX -> frozen IR -> generated C, each step verified."""
